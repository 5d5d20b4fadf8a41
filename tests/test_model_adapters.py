"""The real-model adapters on tiny ONNX models the tests export (the real exports' input / output
signatures, outputs the test controls): every decoding step against an exact expected answer."""

from __future__ import annotations

import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from storage.network_files import ModelFileError, extract_bundled_models, open_onnx
from tasks.perception.models.blazepose import (
    BLAZEPOSE_TO_COCO,
    ROI_SCALE,
    BlazePoseLandmarks,
)
from tasks.perception.models.cliff import CliffEstimator
from tasks.perception.models.composite import ModelPerception
from tasks.perception.models.detector import DecodedBoxesDetector, Detections, YoloxDetector
from tasks.perception.models.image import (
    apply_affine,
    crop_affine,
    invert_affine,
    letterbox,
    nms,
    warp_crops,
)
from tasks.perception.models.keypoints import TopDownKeypoints, refine_dark_udp
from tasks.perception.models.runner import ModelContractError
from tasks.perception.models.segmentation import (
    QueryInstanceMasks,
    SemanticSegmenter,
    assign_masks,
    semantic_person_masks,
)
from tasks.perception.models.settings import (
    BlazePoseSettings,
    DetectorSettings,
    KeypointSettings,
    MaskSettings,
    SemanticSettings,
)

#: the settings the adapters ran with before they took settings objects (udp: ViTPose's codec;
#: box_scale: MediaPipe's region scale)
VITPOSE = KeypointSettings(kind="vitpose", udp=True)
RTMPOSE = KeypointSettings(kind="rtmpose")
BLAZEPOSE = BlazePoseSettings(box_scale=ROI_SCALE)


def export(
    module: torch.nn.Module, args: tuple, path, inputs: list[str], outputs: list[str], dynamic=None
):
    """torch.onnx.export of a small module (the TorchScript exporter: no onnxscript needed)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module.eval(),
            args,
            str(path),
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=dynamic,
            opset_version=17,
            dynamo=False,
        )
    return open_onnx(path, "cpu")


class Const(torch.nn.Module):
    """Outputs fixed tensors (first axis broadcast to the input's batch) whatever the input."""

    def __init__(self, *values):
        super().__init__()
        for i, v in enumerate(values):
            self.register_buffer(f"v{i}", torch.as_tensor(np.asarray(v), dtype=torch.float32))
        self.n = len(values)

    def forward(self, x, *rest):
        zero = x.reshape(x.shape[0], -1)[:, :1] * 0  # (N, 1): ties the outputs to the input's batch
        outs = []
        for i in range(self.n):
            v = getattr(self, f"v{i}")
            outs.append(v + zero.reshape((-1,) + (1,) * (v.dim() - 1)))
        return tuple(outs) if self.n > 1 else outs[0]


def image(h=96, w=128, rgb=(10, 20, 30)):
    return np.broadcast_to(np.array(rgb, np.uint8), (h, w, 3)).copy()


# ---- detection ------------------------------------------------------------------------------


def yolox_rows(C=1):
    """Raw YOLOX rows of a 64 x 64 input (strides 8, 16, 32: 64 + 16 + 4 rows), 5 + C values."""
    rows = np.zeros((84, 5 + C), np.float32)
    rows[:, 4] = 0.01  # background objectness
    a = 2 * 8 + 3  # stride 8, cell (gx 3, gy 2)
    rows[a] = [0.5, 0.5, np.log(2), np.log(4), 0.9, 0.8][: 5 + C]
    b = 2 * 8 + 4  # the neighbour cell, almost the same box, lower score: NMS drops it
    rows[b] = [-0.4, 0.5, np.log(2), np.log(4), 0.8, 0.8][: 5 + C]
    c = 64 + 1 * 4 + 2  # stride 16, cell (2, 1): a separate, weaker box
    rows[c] = [0.0, 0.0, 0.0, 0.0, 0.5, 0.9][: 5 + C]
    return rows


def test_yolox_grid_decoding_letterbox_and_nms(tmp_path):
    runner = export(
        Const(yolox_rows()[None]),
        (torch.zeros(1, 3, 64, 64),),
        tmp_path / "yolox.onnx",
        ["images"],
        ["output"],
    )
    det = YoloxDetector(runner, DetectorSettings(score_threshold=0.3, nms_iou=0.45))(image(96, 128))
    # letterbox ratio min(64/96, 64/128) = 0.5; row a: centre ((0.5+3)8, (0.5+2)8) = (28, 20) in the
    # input, size (2*8, 4*8) = (16, 32) -> image centre (56, 40), size (32, 64)
    # row c: centre (2*16, 1*16) = (32, 16), size (16, 16) -> image centre (64, 32), size (32, 32)
    np.testing.assert_allclose(det.boxes_xyxy, [[40, 8, 72, 72], [48, 16, 80, 48]], atol=1e-4)
    np.testing.assert_allclose(det.scores, [0.72, 0.45], atol=1e-6)


def test_yolox_decoded_export_and_contract(tmp_path):
    rows = np.zeros((3, 6), np.float32)
    rows[0] = [28, 20, 16, 32, 0.9, 0.8]  # already decoded (--decode_in_inference)
    runner = export(
        Const(rows[None]), (torch.zeros(1, 3, 64, 64),), tmp_path / "y.onnx", ["images"], ["output"]
    )
    det = YoloxDetector(runner, DetectorSettings(decoded=True))(image(96, 128))
    np.testing.assert_allclose(det.boxes_xyxy, [[40, 8, 72, 72]], atol=1e-4)
    with pytest.raises(
        ValueError, match="rows"
    ):  # a decoded export read as raw: the row count says so
        YoloxDetector(runner, DetectorSettings())(image(96, 128))
    bad = export(
        Const(np.zeros((1, 17, 8, 6))),
        (torch.zeros(1, 3, 64, 64),),
        tmp_path / "bad.onnx",
        ["images"],
        ["heatmaps"],
    )
    with pytest.raises(ModelContractError, match=r"bad\.onnx: not a YOLOX export"):
        YoloxDetector(bad, DetectorSettings())


def test_yolox_preprocessing_is_the_published_one():
    """Top-left letterbox, padding 114, BGR, no normalisation: what the runner is fed."""

    class Probe:
        source = "probe"
        input_shapes = {"images": (1, 3, 64, 64)}
        output_shapes = {"output": (1, 84, 6)}

        def __call__(self, feeds):
            self.seen = feeds["images"]
            return {"output": np.zeros((1, 84, 6), np.float32)}

    probe = Probe()
    YoloxDetector(probe, DetectorSettings())(image(96, 128, rgb=(10, 20, 30)))
    x = probe.seen[0]
    assert x.shape == (3, 64, 64)
    np.testing.assert_allclose(x[:, :48, :64].reshape(3, -1).mean(1), [30, 20, 10])  # BGR, 0-255
    assert np.all(x[:, 48:, :] == 114)


def test_decoded_boxes_form(tmp_path):
    dets = np.array([[[8, 4, 24, 36, 0.9], [8, 4, 24, 36, 0.95], [0, 0, 10, 10, 0.2]]], np.float32)
    labels = np.array([[0, 2, 0]], np.float32)
    m = Const(dets, labels)
    runner = export(
        m, (torch.zeros(1, 3, 64, 64),), tmp_path / "d.onnx", ["input"], ["dets", "labels"]
    )
    out = DecodedBoxesDetector(runner, DetectorSettings(score_threshold=0.3))(image(96, 128))
    # class 2 dropped, score 0.2 dropped; input box / 0.5
    np.testing.assert_allclose(out.boxes_xyxy, [[16, 8, 48, 72]])
    np.testing.assert_allclose(out.scores, [0.9])


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 20, 30, 30]], float)
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.5).tolist() == [1, 2]
    assert nms(boxes, np.array([0.5, 0.9, 0.3]), 0.9).tolist() == [1, 0, 2]


def test_letterbox_centred_and_mapping_back():
    x, lb = letterbox(image(50, 100), 64, 64, 0.0, center=True)
    assert (lb.scale, lb.pad_x, lb.pad_y) == (0.64, 0.0, 16.0)
    assert np.all(x[:16] == 0) and np.all(x[48:] == 0) and np.allclose(x[16:48], [10, 20, 30])
    np.testing.assert_allclose(lb.to_image([[32.0, 32.0]]), [[50.0, 25.0]])


# ---- crops and keypoints --------------------------------------------------------------------


def test_crop_affine_standard_udp_and_rotation():
    A = crop_affine([[115, 80]], [[56.25, 75]], (32, 24), udp=False)
    np.testing.assert_allclose(
        apply_affine(A, [[[115, 80], [115 - 28.125, 80 - 37.5]]]), [[[12, 16], [0, 0]]]
    )
    U = crop_affine([[115, 80]], [[56.25, 75]], (32, 24), udp=True)
    np.testing.assert_allclose(apply_affine(U, [[[115 + 28.125, 80 + 37.5]]]), [[[23, 31]]])
    R = crop_affine([[0, 0]], [[10, 10]], (10, 10), rotation=[np.pi / 2], udp=False)
    # the region's x axis points down the image (+v): image (0, 1) is 1 px along the crop's +x
    np.testing.assert_allclose(apply_affine(R, [[[0, 1]]]), [[[6, 5]]], atol=1e-12)
    np.testing.assert_allclose(
        apply_affine(invert_affine(R), apply_affine(R, [[[3.0, -2.0]]])), [[[3, -2]]]
    )


def test_warp_crops_samples_bilinearly():
    img = np.zeros((4, 6, 3), np.uint8)
    img[:, :, 0] = np.arange(6) * 10  # red grows along u
    A = crop_affine(
        [[2.5, 1.5]], [[2, 2]], (2, 2), udp=False
    )  # crop pixel (0, 0) <- image (1.5, 0.5)
    out = warp_crops(img, A, (2, 2))
    np.testing.assert_allclose(out[0, :, :, 0], [[15, 25], [15, 25]], atol=1e-4)


def gaussian_maps(n, h, w, centres, sigma=1.5):
    y, x = np.mgrid[0:h, 0:w]
    hm = np.zeros((n, 17, h, w), np.float32)
    for i in range(n):
        for k in range(17):
            cx, cy = centres[i][k]
            hm[i, k] = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
    return hm


def test_dark_refinement_is_exact_on_a_log_quadratic():
    y, x = np.mgrid[0:12, 0:10]
    hm = np.exp(-((x - 4.3) ** 2 + (y - 6.8) ** 2) / 8.0)[None, None]
    got = refine_dark_udp(hm, np.array([[[4.0, 7.0]]]), blur_kernel=0)
    np.testing.assert_allclose(got, [[[4.3, 6.8]]], atol=1e-9)


def test_vitpose_udp_heatmaps_to_image_keypoints(tmp_path):
    h, w = 16, 12
    rng = np.random.default_rng(0)
    centres = rng.uniform(3, 8, size=(2, 17, 2))
    maps = gaussian_maps(2, h, w, centres)
    runner = export(
        Const(maps),
        (torch.zeros(2, 3, 64, 48),),
        tmp_path / "vitpose.onnx",
        ["input"],
        ["heatmaps"],
        dynamic={"input": {0: "n"}, "heatmaps": {0: "n"}},
    )
    boxes = np.array([[100, 50, 130, 110], [20, 30, 60, 70]], np.float32)
    kp = TopDownKeypoints(runner, VITPOSE)(image(200, 300), boxes)
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        # crop: centre, size (w, h) x 1.25 with the short side grown to 48:64; UDP: heatmap k ->
        # image k size / (hm - 1) + centre - size / 2
        cx, cy, bw, bh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * 1.25, (y1 - y0) * 1.25
        sw, sh = (bw, bw / 0.75) if bw > bh * 0.75 else (bh * 0.75, bh)
        want = centres[i] * [sw / (w - 1), sh / (h - 1)] + [cx - sw / 2, cy - sh / 2]
        px_per_cell = sh / (h - 1)
        assert np.abs(kp[i, :, :2] - want).max() < 0.05 * px_per_cell  # the blur's discretisation
    np.testing.assert_allclose(kp[..., 2], maps.max(axis=(2, 3)), atol=1e-6)  # the heatmap maximum


def test_vitpose_classic_quarter_offset(tmp_path):
    maps = np.zeros((1, 17, 16, 12), np.float32)
    maps[0, :, 5, 4] = 0.8
    maps[0, :, 5, 5] = 0.3  # right neighbour higher: +0.25 in x
    maps[0, :, 4, 4] = 0.2  # upper neighbour higher: -0.25 in y
    runner = export(
        Const(maps), (torch.zeros(1, 3, 64, 48),), tmp_path / "hm.onnx", ["input"], ["heatmaps"]
    )
    kp = TopDownKeypoints(runner, KeypointSettings(kind="vitpose", udp=False))(
        image(200, 300), np.array([[100, 50, 130, 110]])
    )
    # heatmap (4.25, 4.75) -> input x4 -> (17, 19); standard crop: centre (115, 80), size (56.25, 75)
    want = np.array([17, 19]) * [56.25 / 48, 75 / 64] + [115 - 28.125, 80 - 37.5]
    np.testing.assert_allclose(kp[0, :, :2], np.broadcast_to(want, (17, 2)), atol=1e-4)
    np.testing.assert_allclose(kp[0, :, 2], 0.8, atol=1e-6)


def test_rtmpose_simcc(tmp_path):
    sx = np.zeros((1, 17, 96), np.float32)
    sy = np.zeros((1, 17, 128), np.float32)
    sx[0, :, 30], sy[0, :, 101] = 0.9, 0.7
    sx[0, 3, 30] = -0.1  # a keypoint whose response is <= 0 has confidence 0
    runner = export(
        Const(sx, sy),
        (torch.zeros(1, 3, 64, 48),),
        tmp_path / "rtm.onnx",
        ["input"],
        ["simcc_x", "simcc_y"],
    )
    kp = TopDownKeypoints(runner, RTMPOSE)(image(200, 300), np.array([[100, 50, 130, 110]]))
    want = np.array([15, 50.5]) * [56.25 / 48, 75 / 64] + [115 - 28.125, 80 - 37.5]
    ok = np.arange(17) != 3
    np.testing.assert_allclose(kp[0, ok, :2], np.broadcast_to(want, (16, 2)), atol=1e-4)
    np.testing.assert_allclose(kp[0, ok, 2], 0.7, atol=1e-6)
    assert kp[0, 3, 2] == 0


def test_keypoints_of_no_box_and_wrong_export(tmp_path):
    maps = np.zeros((1, 17, 16, 12), np.float32)
    runner = export(
        Const(maps), (torch.zeros(1, 3, 64, 48),), tmp_path / "hm.onnx", ["input"], ["heatmaps"]
    )
    assert TopDownKeypoints(runner, VITPOSE)(image(), np.zeros((0, 4))).shape == (0, 17, 3)
    with pytest.raises(ModelContractError, match="RTMPose"):
        TopDownKeypoints(runner, RTMPOSE)


# ---- semantics and masks --------------------------------------------------------------------


def test_semantic_logits_resized_and_argmaxed(tmp_path):
    logits = np.zeros((1, 19, 4, 4), np.float32)
    logits[0, 11, :, :2] = 5.0  # left half person
    logits[0, 0, :, 2:] = 5.0  # right half road
    runner = export(
        Const(logits), (torch.zeros(1, 3, 8, 8),), tmp_path / "seg.onnx", ["input"], ["logits"]
    )
    sem = SemanticSegmenter(runner, SemanticSettings())(image(6, 8))
    assert sem.dtype == np.uint8 and sem.shape == (6, 8)
    assert np.all(sem[:, :4] == 11) and np.all(sem[:, 4:] == 0)


def test_mask2former_queries_to_boxes(tmp_path):
    cls = np.full((1, 3, 3), -5.0, np.float32)
    cls[0, 0, 0] = 5.0  # query 0: person
    cls[0, 1, 2] = 5.0  # query 1: no object
    cls[0, 2, 0] = 5.0  # query 2: person
    masks = np.full((1, 3, 8, 8), -5.0, np.float32)
    masks[0, 0, 1:5, 2:4] = 5.0
    masks[0, 2, 4:8, 5:7] = 5.0
    runner = export(
        Const(cls, masks),
        (torch.zeros(1, 3, 32, 32),),
        tmp_path / "m2f.onnx",
        ["pixel_values"],
        ["class_queries_logits", "masks_queries_logits"],
    )
    boxes = np.array(
        [[10, 8, 13, 15], [4, 2, 7, 9], [0, 0, 2, 2]], np.float32
    )  # q2's, q0's, nobody's
    got = QueryInstanceMasks(runner, MaskSettings(person_class=0))(image(16, 16), boxes)
    want = np.zeros((3, 16, 16), bool)
    want[0, 8:16, 10:14] = True  # query 2 doubled (bilinear edges fall between pixels)
    want[1, 2:10, 4:8] = True  # query 0 doubled
    np.testing.assert_array_equal(got, want)


def test_semantic_person_fallback_nearest_box_wins():
    sem = np.zeros((10, 10), np.uint8)
    sem[2:9, 2:8] = 11
    boxes = np.array(
        [[2, 2, 5, 8], [4, 3, 7, 6]], np.float32
    )  # box 0 reaches lower: it owns the overlap
    got = semantic_person_masks(sem, boxes)
    assert got[0, 4, 4] and not got[1, 4, 4]
    assert got[1, 4, 6] and not got[0, 4, 6]
    assert not (got[0] & got[1]).any()
    # person pixels inside a box: box 0 rows 2-8 x cols 2-5 (28) + box 1's cols 6-7 x rows 3-6 (8)
    assert got.any(0).sum() == 36 and not got.any(0)[7:9, 6:8].any()


def test_assign_masks_one_query_per_box():
    m = np.zeros((2, 8, 8), bool)
    m[0, 0:4, 0:4] = True
    m[1, 4:8, 4:8] = True
    got = assign_masks(np.array([[4, 4, 7, 7], [4, 4, 7, 7], [0, 0, 3, 3]], float), m, 0.5)
    assert got[0].sum() == 16 and got[0, 5, 5] and not got[1].any() and got[2, 0, 0]


# ---- CLIFF ----------------------------------------------------------------------------------


class CliffProbe(torch.nn.Module):
    """Identity rotations, betas[:3] = bbox_info (so the test sees what went in), a fixed camera."""

    def forward(self, img, bbox_info):
        n = img.shape[0]
        rot = torch.eye(3).reshape(1, 1, 3, 3).repeat(n, 24, 1, 1) + 0 * img[:, :1, :1, :1]
        betas = torch.cat([bbox_info, torch.zeros(n, 7)], 1)
        cam = torch.tensor([[0.8, 0.1, -0.2]]).repeat(n, 1) + 0 * bbox_info
        return rot, betas, cam


def test_cliff_inputs_and_conversion(tmp_path):
    runner = export(
        CliffProbe(),
        (torch.zeros(2, 3, 64, 48), torch.zeros(2, 3)),
        tmp_path / "cliff.onnx",
        ["img", "bbox_info"],
        ["pred_rotmat", "pred_betas", "pred_cam"],
        dynamic={
            "img": {0: "n"},
            "bbox_info": {0: "n"},
            "pred_rotmat": {0: "n"},
            "pred_betas": {0: "n"},
            "pred_cam": {0: "n"},
        },
    )
    K = np.array([[700.0, 0, 600], [0, 700, 500], [0, 0, 1]])
    boxes = np.array([[500, 300, 560, 460], [100, 200, 220, 300]], np.float32)
    est = CliffEstimator(runner)(image(1000, 1200), boxes, K)
    c = (boxes[:, :2] + boxes[:, 2:]) / 2
    b = np.maximum((boxes[:, 2] - boxes[:, 0]) * 64 / 48, boxes[:, 3] - boxes[:, 1]) * 1.1
    info = np.stack(
        [(c[:, 0] - 600) / 700 * 2.8, (c[:, 1] - 500) / 700 * 2.8, (b - 0.24 * 700) / (0.06 * 700)],
        1,
    )
    np.testing.assert_allclose(est.betas[:, :3], info, rtol=1e-5)
    sb = 0.8 * b
    want_t = np.stack(
        [0.1 + 2 * (c[:, 0] - 600) / sb, -0.2 + 2 * (c[:, 1] - 500) / sb, 2 * 700 / sb], 1
    )
    np.testing.assert_allclose(est.transl, want_t, rtol=1e-5)
    np.testing.assert_allclose(est.body_pose, 0, atol=1e-6)


# ---- BlazePose ------------------------------------------------------------------------------


def test_blazepose_landmarks_on_a_fake_runner():
    """Landmarks at known crop pixels come back at the expected image pixels; COCO order; the
    pose flag gates the confidences; the segmentation comes back as the box's mask."""

    class Fake:
        source = "fake"
        input_shapes = {"input_1": (1, 256, 256, 3)}
        output_shapes = {
            "Identity": (1, 195),
            "Identity_1": (1, 1),
            "Identity_2": (1, 256, 256, 1),
            "Identity_3": (1, 64, 64, 39),
            "Identity_4": (1, 117),
        }

        def __init__(self, flag):
            self.flag = flag

        def __call__(self, feeds):
            lm = np.zeros((39, 5), np.float32)
            lm[:, 0] = np.arange(39) * 4 + 32.5  # x in crop pixels (corner convention)
            lm[:, 1] = 128.5
            lm[:, 3] = 3.0  # visibility logit
            seg = np.full((1, 256, 256, 1), -8.0, np.float32)
            seg[0, 64:192, 96:160] = 8.0
            return {
                "Identity": lm.reshape(1, 195),
                "Identity_1": np.array([[self.flag]], np.float32),
                "Identity_2": seg,
                "Identity_3": np.full((1, 64, 64, 39), -8.0, np.float32),
                "Identity_4": np.zeros((1, 117), np.float32),
            }

    box = np.array([[100, 100, 164, 228]], np.float32)  # 64 x 128: the square region is 160 x 160
    kp, masks, flag = BlazePoseLandmarks(Fake(0.9), BLAZEPOSE)(image(300, 300), box)
    # crop px x -> image: centre 132 + (x - 128) * 160 / 256
    want_u = 132 + (np.arange(39)[list(BLAZEPOSE_TO_COCO)] * 4 + 32.5 - 128) * 160 / 256
    np.testing.assert_allclose(kp[0, :, 0], want_u, atol=1e-4)
    np.testing.assert_allclose(kp[0, :, 1], 164 + (128.5 - 128) * 160 / 256, atol=1e-4)
    np.testing.assert_allclose(kp[0, :, 2], 1 / (1 + np.exp(-3.0)), atol=1e-6)
    assert flag[0] == pytest.approx(0.9)
    # the crop's person rectangle, edges at crop 95.5 / 159.5 (u) and 63.5 / 191.5 (v) -> image
    # u 112 / 152, v 124 / 204 (probability exactly 0.5 on those lines)
    inside = np.zeros((300, 300), bool)
    inside[125:204, 113:152] = True
    outside = np.ones((300, 300), bool)
    outside[124:205, 112:153] = False
    assert masks[0][inside].all() and not masks[0][outside].any()
    kp, _, _ = BlazePoseLandmarks(Fake(0.2), BLAZEPOSE)(image(300, 300), box)
    assert np.all(kp[0, :, 2] == 0)  # no pose in the region: no confidence
    comp = ModelPerception(blazepose=BlazePoseLandmarks(Fake(0.2), BLAZEPOSE))(
        image(300, 300), Detections(box, np.ones(1, np.float32))
    )
    assert len(comp) == 0 and comp.semantic.shape == (300, 300) and np.all(comp.semantic == 255)


# ---- composite and files --------------------------------------------------------------------


def test_composite_yolox_vitpose_semantic_fallback(tmp_path):
    yolox = YoloxDetector(
        export(
            Const(yolox_rows()[None]),
            (torch.zeros(1, 3, 64, 64),),
            tmp_path / "y.onnx",
            ["images"],
            ["output"],
        ),
        DetectorSettings(),
    )
    maps = gaussian_maps(1, 16, 12, [np.full((17, 2), 5.0)])
    vit = TopDownKeypoints(
        export(
            Const(maps), (torch.zeros(1, 3, 64, 48),), tmp_path / "v.onnx", ["input"], ["heatmaps"]
        ),
        VITPOSE,
    )
    logits = np.zeros((1, 19, 4, 4), np.float32)
    logits[0, 11] = 5.0
    seg = SemanticSegmenter(
        export(
            Const(logits), (torch.zeros(1, 3, 8, 8),), tmp_path / "s.onnx", ["input"], ["logits"]
        ),
        SemanticSettings(),
    )
    out = ModelPerception(detector=yolox, keypoints=vit, semantic=seg)(image(96, 128))
    assert len(out) == 2 and out.keypoints.shape == (2, 17, 3) and np.all(out.semantic == 11)
    # the semantic person pixels of each box (box 0 [40, 72] x [8, 72] reaches lower: it owns the overlap)
    assert out.masks[0, 8:73, 40:73].all() and out.masks[0].sum() == 33 * 65
    assert out.masks[1].sum() == (33 * 33) - (73 - 48) * (49 - 16)


def test_model_file_errors_name_the_file(tmp_path):
    with pytest.raises(ModelFileError, match="nothing.onnx: model file not found"):
        open_onnx(tmp_path / "nothing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelFileError, match="junk.onnx: not a loadable ONNX model"):
        open_onnx(junk)
    with pytest.raises(ModelFileError, match="device 'cuda'"):
        runner = export(
            Const(np.zeros((1, 2))), (torch.zeros(1, 3, 4, 4),), tmp_path / "c.onnx", ["x"], ["y"]
        )
        open_onnx(runner.source, "cuda")


def test_bundled_extraction_checks_the_wheel(tmp_path):
    wheel = tmp_path / "mediapipe-0.10.21-fake.whl"
    with zipfile.ZipFile(wheel, "w") as zf:
        zf.writestr("mediapipe/modules/pose_detection/pose_detection.tflite", b"tampered")
    with pytest.raises(ModelFileError, match="has sha256"):
        extract_bundled_models(wheel, tmp_path / "cache")
    assert not (tmp_path / "cache" / "pose_detection.tflite").exists()


def test_cli_unpacks_the_bundled_models(tmp_path, capsys):
    """`mobileocc models unpack-bundled` (what set-up runs): a wheel holding the right files ->
    both extracted, paths printed; a tampered one -> exit 1 naming the wheel."""
    from flows.cli import main
    from storage.network_files import BUNDLED_MODELS, DEFAULT_BUNDLED_CACHE

    bad = tmp_path / "mediapipe-0.10.21-bad.whl"
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("mediapipe/modules/pose_detection/pose_detection.tflite", b"tampered")
    cmd = ["models", "unpack-bundled", "--cache", str(tmp_path / "cache")]
    assert main([*cmd, "--wheel", str(bad)]) == 1
    assert f"{bad}: mediapipe/modules/pose_detection" in capsys.readouterr().err
    have = Path(__file__).resolve().parents[1] / DEFAULT_BUNDLED_CACHE
    if not all((have / n).is_file() for n in BUNDLED_MODELS):
        pytest.skip(f"bundled models not extracted to {have} (make setup does it)")
    good = tmp_path / "mediapipe-0.10.21-good.whl"
    with zipfile.ZipFile(good, "w") as zf:
        for name, (member, _) in BUNDLED_MODELS.items():
            zf.writestr(member, (have / name).read_bytes())
    assert main([*cmd, "--wheel", str(good)]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(tmp_path / "cache" / n) for n in BUNDLED_MODELS]
    for name in BUNDLED_MODELS:
        assert (tmp_path / "cache" / name).read_bytes() == (have / name).read_bytes()


def test_bundled_models_are_found_from_another_working_directory(tmp_path, monkeypatch):
    """The default cache is relative: a run from a data folder (not the checkout) takes the files
    `make setup` extracted into the checkout; where neither place has one, the error names both."""
    from storage.network_files import BUNDLED_MODELS, DEFAULT_BUNDLED_CACHE, bundled_model

    monkeypatch.chdir(tmp_path)
    have = Path(__file__).resolve().parents[1] / DEFAULT_BUNDLED_CACHE
    with pytest.raises(ModelFileError, match=r"missing") as err:
        bundled_model("no/such/cache", "pose_detection.tflite")
    assert str(tmp_path / "no/such/cache") not in str(err.value)  # relative, as configured
    assert str(have.parents[2] / "no/such/cache/pose_detection.tflite") in str(err.value)
    if not all((have / n).is_file() for n in BUNDLED_MODELS):
        pytest.skip(f"bundled models not extracted to {have} (make setup does it)")
    for name in BUNDLED_MODELS:
        assert bundled_model(DEFAULT_BUNDLED_CACHE, name) == have / name
    here = tmp_path / DEFAULT_BUNDLED_CACHE
    here.mkdir(parents=True)
    # a copy of its own (a damaged one is refused: the files are verified by sha256)
    (here / "pose_detection.tflite").write_bytes((have / "pose_detection.tflite").read_bytes())
    assert bundled_model(DEFAULT_BUNDLED_CACHE, "pose_detection.tflite").resolve() == (
        here / "pose_detection.tflite"
    )


def test_model_detections_take_ground_truth_identities_by_box():
    """Synthetic data: a model detection starts its fit from the oracle's body of the person its
    box matches (IoU >= 0.5); unmatched detections and persons out of view take none."""
    from flows.stages.models import gt_index_by_boxes

    gt = np.array([[0, 0, 10, 20], [np.nan] * 4, [30, 0, 40, 20]], np.float32)
    det = np.array([[31, 0, 41, 20], [100, 100, 110, 120], [0, 1, 10, 21]], np.float32)
    assert gt_index_by_boxes(det, gt).tolist() == [2, -1, 0]

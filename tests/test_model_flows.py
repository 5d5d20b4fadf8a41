"""The real-model providers inside the pipeline: the bundled BlazePose models on the synthetic
frames (detect.image_provider 'models', LiDAR boxes as proposals) and a CLIFF export that the
test makes (fit.init_provider 'cliff')."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import torch

from configs.schema import load_config
from flows.pipeline.run import rebuild_dataset
from storage.manifest import Manifest
from storage.network_files import BUNDLED_MODELS, DEFAULT_BUNDLED_CACHE
from storage.products import Detections

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / DEFAULT_BUNDLED_CACHE

pytestmark = [
    pytest.mark.usefixtures("prefect_harness"),
    pytest.mark.xdist_group("prefect"),
    pytest.mark.slow,
    pytest.mark.skipif(
        not all((BUNDLED / n).is_file() for n in BUNDLED_MODELS),
        reason=f"bundled models not extracted to {BUNDLED} (make setup does it)",
    ),
]


class UprightCliff(torch.nn.Module):
    """A CLIFF-shaped export: an upright body (180 deg about x: SMPL's y-up into the camera's
    y-down), mean shape, a crop camera that puts it ~2 f / (s b) away."""

    def forward(self, img, bbox_info):
        n = img.shape[0]
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
        rot = torch.eye(3).reshape(1, 1, 3, 3).repeat(n, 24, 1, 1)
        rot[:, 0] = flip
        rot = rot + 0 * img[:, :1, :1, :1]
        return (
            rot,
            torch.zeros(n, 10) + 0 * bbox_info[:, :1],
            torch.tensor([[1.0, 0.0, 0.0]]).repeat(n, 1),
        )


def test_bundled_models_and_cliff_in_the_flow(copy_dataset, tmp_path):
    data = copy_dataset()
    cliff = tmp_path / "cliff.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            UprightCliff(),
            (torch.zeros(1, 3, 256, 192), torch.zeros(1, 3)),
            str(cliff),
            input_names=["img", "bbox_info"],
            output_names=["pred_rotmat", "pred_betas", "pred_cam"],
            dynamic_axes={
                k: {0: "n"} for k in ("img", "bbox_info", "pred_rotmat", "pred_betas", "pred_cam")
            },
            opset_version=17,
            dynamo=False,
        )
    out = tmp_path / "out"
    cfg = load_config(
        ROOT / "configs" / "bundled-models.yaml",
        overrides={
            "dataset.root": str(data),
            "output.root": str(out),
            "fit.iterations": 5,
            "detect.models.bundled_dir": str(BUNDLED),
            "detect.models.device": "cpu",
            "fit.init_provider": "cliff",
            "fit.cliff_path": str(cliff),
            "fit.max_shift_m": None,
        },
    )
    report = rebuild_dataset(
        cfg, progress=False, sequences=["1"]
    )  # one sequence: 2 frames, 3 people
    assert all(o.status == "done" for o in report.outcomes.values()), report.outcomes
    manifest = Manifest.load(out)
    dets = fitted = 0
    for seq in ("1",):
        detect = out / manifest.get(seq, "detect").location
        summary = json.loads((detect / "summary.json").read_text())
        assert summary["image_provider"] == "models"
        for f in sorted(detect.glob("frame_*.npz")):
            d = Detections.read(detect, f.stem).arrays()
            dets += len(d["scores"])
            if len(d["scores"]):
                # BlazePose's keypoints lie in (or near) their boxes and its masks are not empty
                b, kp = d["boxes_xyxy"], d["keypoints"]
                conf = kp[..., 2] > 0.5
                inside = (
                    (kp[..., 0] >= b[:, None, 0] - 20)
                    & (kp[..., 0] <= b[:, None, 2] + 20)
                    & (kp[..., 1] >= b[:, None, 1] - 20)
                    & (kp[..., 1] <= b[:, None, 3] + 20)
                )
                assert conf.any() and inside[conf].mean() > 0.9
                assert all((d["mask_labels"] == k + 1).any() for k in range(len(b)))
        fit = json.loads((out / manifest.get(seq, "fit").location / "summary.json").read_text())
        assert fit["skipped_without_estimate"] == 0  # CLIFF estimates every tracked box
        fitted += fit["fitted"]
    assert dets > 0 and fitted > 0

"""Draw one frame (storage.viewer_data.FrameData) into a viser scene.

The scene's world is the frame's base frame (x forward, y left, z up, metres). Three groups:

- ``/labels``: the dataset's voxels (class colours; optionally only inside mask_camera /
  mask_lidar; unknown space as grey), the fitted bodies coloured by track id with their boxes,
  per-voxel velocity arrows; with ``/sensors``: the LiDAR sweep and the camera frustum and image;
- ``/gt``: the simulator's ground truth (voxels and bodies), beside the labels (shifted to the
  right, -y, by the grid's width and a gap);
- ``/diff``: the difference of labels and ground truth (correct / wrong class / missed / extra,
  the report's colours), one more width to the right: prediction | ground truth | difference from
  left to right, as in the report's BEV figure.

What is drawn comes from tasks.view.scene; this module only places it. Each call replaces the
previous frame's nodes and removes those the new frame does not have.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from tasks import conventions as C
from tasks.view import scene as S
from tasks.viz import instance_colors

#: the unit cube every voxel instance scales (12 triangles)
CUBE_VERTICES = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32
)
CUBE_FACES = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ],  # fmt: skip
    np.uint32,
)
#: gap between the labels, the ground truth and the difference, m
GROUP_GAP_M = 1.0
#: LiDAR points are shown this far around the grid (a sweep reaches 100 m), m
LIDAR_MARGIN_M = 3.0
#: voxels at least this big go to the browser as float16 points (quantised to <= 8 mm at 20 m)
FLOAT16_MIN_VOXEL_M = 0.1


@dataclass(frozen=True)
class Layers:
    """What to draw. mask: "none" (every occupied voxel), "camera" or "lidar" (only voxels where
    that mask is 1); style: "points" (unlit squares of the voxel's size: the class colours as
    they are, 9 bytes a voxel) or "cubes" (instanced lit boxes: shaded, but viser's lighting
    pales the colours, 31 bytes a voxel); max_voxels: per voxel layer, beyond it voxels merge
    into blocks (tasks.view.scene)."""

    voxels: bool = True
    pedestrian_voxels: bool = True
    mask: str = "none"
    unknown: bool = False
    bodies: bool = True
    boxes: bool = True
    velocity: bool = True
    lidar: bool = True
    camera: bool = True
    ground_truth: bool = True
    difference: bool = True
    style: str = "points"
    max_voxels: int = S.MAX_VOXELS

    def __post_init__(self) -> None:
        if self.mask not in ("none", "camera", "lidar"):
            raise ValueError(f"mask {self.mask!r}: expected none, camera or lidar")
        if self.style not in ("points", "cubes"):
            raise ValueError(f"style {self.style!r}: expected points or cubes")

    def with_(self, **kw) -> Layers:
        return replace(self, **kw)


@dataclass
class DrawStats:
    """What one frame put in the scene: per voxel layer (labels, unknown, gt, diff) its counts
    (VoxelLayer fields), bodies, arrows, LiDAR points, and the seconds it took."""

    layers: dict[str, dict] = field(default_factory=dict)
    bodies: int = 0
    arrows: int = 0
    points: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def group_offset(data) -> float:
    """How far right (-y) the ground truth is shifted: the grid's width plus a gap, m."""
    return float(data.semantics.shape[1] * data.voxel_size_m + GROUP_GAP_M)


def view_center(data) -> np.ndarray:
    """(3,) centre of the labels' grid, base frame, m."""
    return data.range_min + np.asarray(data.semantics.shape) * data.voxel_size_m / 2.0


def posed_bodies(model, persons: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Fitted bodies of the frame's instances rows -> (track ids (B,), vertices (B, V, 3) base
    frame); rows without body parameters (not fitted) are left out."""
    from tasks.body.posing import posed_vertices

    rows = [r for r in persons if r.get("betas") is not None and r.get("transl") is not None]
    if model is None or not rows:
        return np.zeros(0, np.int64), np.zeros((0, 0, 3), np.float32)
    arr = {
        k: np.asarray([r[k] for r in rows], np.float32)
        for k in ("betas", "global_orient", "body_pose", "transl")
    }
    verts = posed_vertices(
        model, arr["betas"], arr["global_orient"], arr["body_pose"], arr["transl"]
    )
    return np.asarray([int(r["track_id"]) for r in rows]), verts


class FrameDrawer:
    """Draws frames into ``scene`` (a viser SceneApi), replacing the previous frame's nodes."""

    def __init__(self, scene, body_model=None, faces: np.ndarray | None = None):
        self.scene = scene
        self.model = body_model
        self.faces = (
            np.asarray(body_model.faces, np.uint32)
            if body_model is not None
            else (None if faces is None else np.asarray(faces, np.uint32))
        )
        self.handles: dict[str, object] = {}
        self.camera = None  # the last CameraView drawn (QA clicks)

    def clear(self) -> None:
        for handle in self.handles.values():
            handle.remove()
        self.handles = {}

    def draw(self, data, layers: Layers) -> DrawStats:
        t0 = time.perf_counter()
        stats = DrawStats(notes=list(data.notes))
        new: dict[str, object] = {}
        rm, vs = data.range_min, data.voxel_size_m
        offset = group_offset(data)
        add = self._adder(new)

        if layers.voxels:
            mask = {"none": None, "camera": data.mask_camera, "lidar": data.mask_lidar}[layers.mask]
            sem = data.semantics
            if not layers.pedestrian_voxels:  # to see the bodies inside them
                sem = np.where(sem == C.PEDESTRIAN, np.uint8(C.FREE), sem)
            layer = S.class_layer(sem, rm, vs, mask, True, layers.max_voxels)
            self._voxels(add, "/labels/voxels", layer, layers, stats)
        if layers.unknown:
            mask = data.mask_lidar if layers.mask == "lidar" else data.mask_camera
            layer = S.unknown_layer(data.semantics, mask, rm, vs, layers.max_voxels)
            self._voxels(add, "/labels/unknown", layer, layers, stats)
        if layers.bodies or layers.boxes:
            self._people(add, data, layers, stats)
        if layers.velocity:
            arrows, _ = S.velocity_arrows(data.semantics, data.velocity, rm, vs)
            stats.arrows = len(arrows)
            if len(arrows):
                add(
                    "/labels/velocity",
                    lambda n: self.scene.add_arrows(
                        n,
                        arrows,
                        colors=(20, 20, 20),
                        shaft_radius=min(0.02, vs / 4),
                        head_radius=min(0.05, vs / 2),
                        head_length=min(0.1, vs),
                    ),
                )
        if layers.lidar and data.points_lidar is not None:
            lo = rm - LIDAR_MARGIN_M
            hi = rm + np.asarray(data.semantics.shape) * vs + LIDAR_MARGIN_M
            pts, cols = S.lidar_points(data.points_lidar, data.T_base_from_lidar, 60_000, lo, hi)
            stats.points = len(pts)
            add(
                "/sensors/lidar",
                lambda n: self.scene.add_point_cloud(
                    n, pts, cols, point_size=0.025, point_shape="circle", point_shading="flat"
                ),
            )
        if layers.camera:
            self._camera(add, data)
        if data.gt is not None and (layers.ground_truth or layers.difference):
            self._ground_truth(add, data, layers, offset, stats)

        for name in set(self.handles) - set(new):
            self.handles[name].remove()
        self.handles = new
        stats.seconds = time.perf_counter() - t0
        return stats

    # ---- pieces --------------------------------------------------------------------------------

    def _adder(self, new: dict):
        def add(name: str, make):
            new[name] = make(name)
            return new[name]

        return add

    def _voxels(
        self, add, name: str, layer: S.VoxelLayer, layers: Layers, stats: DrawStats, dy: float = 0
    ):
        key = name.strip("/").replace("/", "_")
        stats.layers[key] = {
            "shown": len(layer),
            "selected": layer.selected,
            "surface": layer.surface,
            "block": layer.block,
        }
        if len(layer) == 0:
            return
        # positions in the world, never as a node offset: viser's recorded pages lose node
        # offsets of point clouds when their timeline loops (seen in Chromium: every layer
        # jumped to the origin); float16 keeps ~8 mm at 20 m, enough for 0.1 m voxels
        pts = layer.centers + np.array([0.0, dy, 0.0], np.float32)
        precision = "float16" if layer.size_m >= FLOAT16_MIN_VOXEL_M else "float32"
        stats.layers[key]["style"] = layers.style
        if layers.style == "cubes":
            add(
                name,
                lambda n: self.scene.add_batched_meshes_simple(
                    n,
                    CUBE_VERTICES * layer.size_m,
                    CUBE_FACES,
                    batched_wxyzs=np.broadcast_to(
                        np.array([1.0, 0, 0, 0], np.float32), (len(layer), 4)
                    ),
                    batched_positions=pts,
                    batched_colors=layer.colors,
                    lod="off",
                    flat_shading=True,
                    cast_shadow=False,
                    receive_shadow=False,
                ),
            )
        else:
            add(
                name,
                lambda n: self.scene.add_point_cloud(
                    n,
                    pts,
                    layer.colors,
                    point_size=layer.size_m,
                    point_shape="square",
                    point_shading="flat",
                    precision=precision,
                ),
            )

    def _people(self, add, data, layers: Layers, stats: DrawStats) -> None:
        if layers.bodies and self.model is not None:
            ids, verts = posed_bodies(self.model, data.persons)
            colors = instance_colors(ids)
            stats.bodies = len(ids)
            for tid, v, col in zip(ids, verts, colors):
                add(
                    f"/labels/bodies/track_{tid}",
                    lambda n, v=v, col=col: self.scene.add_mesh_simple(
                        n, v, self.faces, color=tuple(int(c) for c in col), cast_shadow=False
                    ),
                )
        boxed = [r for r in data.persons if r.get("box3d_center") is not None]
        if layers.boxes and boxed:
            segs = S.box_segments(
                [r["box3d_center"] for r in boxed],
                [r["box3d_size"] for r in boxed],
                [r["box3d_yaw"] for r in boxed],
            )
            cols = np.repeat(instance_colors([int(r["track_id"]) for r in boxed]), 12, axis=0)
            add(
                "/labels/boxes",
                lambda n: self.scene.add_line_segments(
                    n,
                    segs,
                    np.repeat(cols[:, None], 2, axis=1),
                    thickness=2.0,
                    thickness_units="screen",
                ),
            )
            for r in boxed:
                top = np.asarray(r["box3d_center"]) + [0, 0, r["box3d_size"][2] / 2 + 0.15]
                add(
                    f"/labels/ids/track_{r['track_id']}",
                    lambda n, r=r, top=top: self.scene.add_label(
                        n, f"#{r['track_id']}", position=tuple(top)
                    ),
                )

    def _camera(self, add, data) -> None:
        cam = S.camera_view(data.K, data.width, data.height, data.T_base_from_cam0)
        self.camera = cam
        add(
            "/sensors/camera",
            lambda n: self.scene.add_camera_frustum(
                n,
                fov=cam.fov_y,
                aspect=cam.aspect,
                scale=frustum_scale(cam),
                color=(40, 40, 40),
                thickness=0.01,
                wxyz=cam.wxyz,
                position=cam.position,
            ),
        )
        if data.image is not None:
            small = _shrink(data.image, 480)
            add(
                "/sensors/image",
                lambda n: self.scene.add_image(
                    n,
                    small,
                    render_width=cam.image_size_m[0],
                    render_height=cam.image_size_m[1],
                    format="jpeg",
                    jpeg_quality=80,
                    cast_shadow=False,
                    receive_shadow=False,
                    wxyz=cam.wxyz,
                    position=cam.image_center,
                ),
            )

    def _ground_truth(self, add, data, layers: Layers, offset: float, stats: DrawStats) -> None:
        rm, vs, gt = data.range_min, data.voxel_size_m, data.gt
        top = view_center(data) + [0, 0, data.semantics.shape[2] * vs / 2 + 0.3]
        shift = np.array([0.0, -offset, 0.0])
        if layers.ground_truth:
            layer = S.class_layer(gt.occupancy, rm, vs, None, True, layers.max_voxels)
            self._voxels(add, "/gt/voxels", layer, layers, stats, -offset)
            add(
                "/gt/title",
                lambda n: self.scene.add_label(n, "ground truth", position=tuple(top + shift)),
            )
            if layers.bodies and self.faces is not None and gt.faces.shape == self.faces.shape:
                for tid, v, col in zip(gt.track_id, gt.vertices, instance_colors(gt.track_id)):
                    add(
                        f"/gt/bodies/track_{tid}",
                        lambda n, v=v, col=col: self.scene.add_mesh_simple(
                            n,
                            v + shift.astype(np.float32),  # in place, not a node offset
                            self.faces,
                            color=tuple(int(c) for c in col),
                            cast_shadow=False,
                        ),
                    )
        if layers.difference:
            mask = {"none": None, "camera": data.mask_camera, "lidar": data.mask_lidar}[layers.mask]
            layer = S.difference_layer(
                data.semantics, gt.occupancy, rm, vs, mask, layers.max_voxels
            )
            self._voxels(add, "/diff/voxels", layer, layers, stats, -2 * offset)
            counts = {
                name: int(np.sum(layer.codes == code))
                for code, name in ((1, "correct"), (2, "wrong class"), (3, "missed"), (4, "extra"))
            }
            text = "difference: " + ", ".join(f"{k} {v}" for k, v in counts.items())
            add(
                "/diff/title",
                lambda n: self.scene.add_label(n, text, position=tuple(top + 2 * shift)),
            )


def frustum_scale(cam: S.CameraView) -> float:
    """The frustum ``scale`` that puts viser's drawn image plane at ``cam.depth_m``: viser draws
    the far plane at depth scale / cbrt(tan(fov/2)^2 * aspect / 3) (its CameraFrustum)."""
    t = np.tan(cam.fov_y / 2.0)
    return float(cam.depth_m * np.cbrt(t * t * cam.aspect / 3.0))


def _shrink(image: np.ndarray, height: int) -> np.ndarray:
    from tasks.viz import resize_nearest

    return image if image.shape[0] <= height else resize_nearest(image, height)

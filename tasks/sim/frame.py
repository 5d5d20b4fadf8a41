"""One simulated frame: pose the people, ray-cast the sensors, compute the exact ground truth.

:class:`Simulator` is built once per sequence from :class:`~tasks.sim.scene.SimOptions`; every
frame is a pure function of (options, frame index), so frames may be made in any order or in
parallel. Times: t = index / frame_rate_hz seconds since the first frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch

from tasks import conventions as C
from tasks.geometry import make_transform, rot_x, rot_z, transform_points
from tasks.sim import groundtruth as G
from tasks.sim.geometry import rotation_to_axis_angle
from tasks.sim.scene import LabelledObject, Scene, SimOptions, build_scene, pedestrian_state
from tasks.sim.sensors import (
    ALBEDO,
    CameraRays,
    CameraRender,
    LidarSweep,
    MeshSet,
    SensorRig,
    cast_lidar,
    make_rig,
    render_camera,
)

#: half the time step of the central difference behind the per-vertex velocities, s: the posed body
#: is a smooth function of time (except where a walk starts or stops), so the truncation error
#: (~h^2 times the third derivative) is below the float32 rounding of the vertices over 2 h (~1e-4 m/s)
VERTEX_VELOCITY_STEP_S = 1e-3

#: COCO-17 keypoints taken from SMPL joints (the face ones come from vertices).
_COCO_JOINT_IDX = np.array([C.COCO_TO_SMPL_JOINT[i] for i in range(5, 17)])


@dataclass(frozen=True)
class PeopleFrame:
    """All K people of a frame (stacked; K may be 0). LiDAR frame of the frame unless named.

    track_id (K,) int32; betas (K, 10), global_orient (K, 3), body_pose (K, 69), transl (K, 3)
    float32 (body-model parameters that reproduce ``vertices``); vertices (K, V, 3), joints
    (K, 24, 3) float32 m; velocity_base (K, 2) float32 m/s (world velocity in base axes);
    box2d (K, 4) float32 cam0 px xyxy of the projected body clipped to the image (NaN when not
    in view); keypoints (K, 17, 3) float32 (u, v, flag 0/1/2) cam0; visible_fraction (K,) float32
    visible / full silhouette pixels in cam0; box_center (K, 3), box_size (K, 3) (l, w, h),
    box_yaw (K,) float32 (rad); occlusion: CODa isOccluded per person. vertex_velocity_base
    (K, V, 3) float32 m/s: each vertex's world velocity in base axes (Simulator.vertex_velocity_base).
    """

    track_id: np.ndarray
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    velocity_base: np.ndarray
    box2d: np.ndarray
    keypoints: np.ndarray
    visible_fraction: np.ndarray
    box_center: np.ndarray
    box_size: np.ndarray
    box_yaw: np.ndarray
    occlusion: tuple[str, ...]
    vertex_velocity_base: np.ndarray | None = None


@dataclass(frozen=True)
class ObjectBox:
    """A labelled static thing in the LiDAR frame: center (3,), size (l, w, h), yaw rad."""

    obj: LabelledObject
    center: np.ndarray
    yaw: float


@dataclass(frozen=True)
class SimFrame:
    """Everything one frame produces. Poses (4, 4) float64; grids (X, Y, Z) in the base frame
    (occupancy uint8 class ids with 10 free, occupancy_instance uint16 track ids)."""

    index: int
    t_s: float
    T_world_from_lidar: np.ndarray
    T_world_from_base: np.ndarray
    sweep: LidarSweep
    cam0: CameraRender
    cam1: CameraRender
    occupancy: np.ndarray
    occupancy_instance: np.ndarray
    people: PeopleFrame
    objects: tuple[ObjectBox, ...]


def _body_pose(seed: int, spec, state) -> np.ndarray:
    """(69,) axis-angle pose of a person at a state: gait while moving, else standing (a fixed
    per-person variation) or gesturing with the arms."""
    from tasks.body.poses import arm_swing_pose, gait_pose, standing_pose

    if state.moving:
        return gait_pose(state.phase % 1.0, max(spec.speed_mps, 0.3))
    rng = np.random.default_rng([seed, spec.track_id, 0x57A])
    if spec.gesturing:
        return arm_swing_pose(state.phase % 1.0, rng)
    return standing_pose(rng)


class Simulator:
    """Generates the frames of one synthetic sequence.

    options: the sequence; body_model: a tasks.body BodyModel (default: the procedural one);
    grid: the ground-truth occupancy grid (base frame); rig: the sensors (default from
    ``options.sensor``).
    """

    def __init__(
        self,
        options: SimOptions,
        body_model=None,
        grid: G.GridSpec = G.GridSpec(),
        rig: SensorRig | None = None,
    ):
        if body_model is None:
            from tasks.body.procedural import default_body_model

            body_model = default_body_model()
        self.options = options
        self.scene: Scene = build_scene(options)
        self.rig = rig or make_rig(options.sensor)
        self.grid = grid
        self.model = body_model
        self.person_faces = np.asarray(body_model.faces, dtype=np.int64)
        self._rays: dict[str, CameraRays] = {}  # made on the first frame (poses need none)
        self._static = self._static_meshes()

    # ---------------------------------------------------------------- static geometry
    def _static_meshes(self):
        rng = np.random.default_rng(np.random.SeedSequence([self.options.seed, 0xC01]))
        verts, faces, cls, inst, alb, boxes = [], [], [], [], [], []
        offset = 0
        items = [(s, False) for s in self.scene.surfaces] + [(s, True) for s in self.scene.solids]
        colours: dict[int, np.ndarray] = {}
        for item, solid in items:
            base = ALBEDO[item.class_id]
            if (
                item.class_id in (C.CAR, C.OTHER_STRUCTURE, C.TWO_WHEELER, C.TRUCK)
                and item.instance_id
            ):
                if item.instance_id not in colours:
                    jitter = (
                        rng.uniform(0.6, 1.3, 3)
                        if item.class_id == C.CAR
                        else rng.uniform(0.85, 1.1, 3)
                    )
                    colours[item.instance_id] = np.clip(base * jitter, 0, 1)
                base = colours[item.instance_id]
            if item.class_id == C.VEGETATION and len(item.vertices) <= 16:
                base = np.array([0.4, 0.28, 0.16])  # trunk
            verts.append(item.vertices)
            faces.append(item.faces + offset)
            offset += len(item.vertices)
            nf = len(item.faces)
            cls.append(np.full(nf, item.class_id, np.uint8))
            inst.append(np.full(nf, item.instance_id, np.uint16))
            alb.append(np.broadcast_to(np.asarray(base, np.float32), (nf, 3)))
            lo, hi = item.vertices.min(0), item.vertices.max(0)
            boxes.append((lo, hi, item, solid))
        return dict(
            vertices=np.concatenate(verts),
            faces=np.concatenate(faces),
            cls=np.concatenate(cls),
            inst=np.concatenate(inst),
            albedo=np.concatenate(alb).astype(np.float32),
            items=boxes,
        )

    # ---------------------------------------------------------------- poses
    def robot_pose(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(T_world_from_base, T_world_from_lidar) of a frame, (4, 4) float64."""
        t_s = index / self.options.frame_rate_hz
        xy = self.scene.robot_xy(t_s)
        T_wb = make_transform(np.eye(3), [xy[0], xy[1], 0.0])
        return T_wb, T_wb @ self.rig.T_base_from_lidar

    def _pose_people(self, t_s: float, T_world_from_lidar: np.ndarray):
        specs = self.scene.pedestrians
        K = len(specs)
        if K == 0:
            return None
        states = [pedestrian_state(s, t_s) for s in specs]
        betas = torch.as_tensor(np.stack([s.betas for s in specs]), dtype=torch.float32)
        body_pose = np.stack(
            [_body_pose(self.options.seed, sp, st) for sp, st in zip(specs, states)]
        )
        R_w = np.stack([rot_z(st.heading + np.pi / 2) @ rot_x(np.pi / 2) for st in states])
        go_w = np.stack([rotation_to_axis_angle(R) for R in R_w])
        bp = torch.as_tensor(body_pose, dtype=torch.float32)
        with torch.no_grad():
            out0 = self.model(
                betas, torch.as_tensor(go_w, dtype=torch.float32), bp, torch.zeros(K, 3)
            )
        v0 = out0.vertices.numpy().astype(np.float64)
        j0 = out0.joints.numpy().astype(np.float64)
        transl_w = np.stack(
            [
                [st.xy[0] - j0[k, 0, 0], st.xy[1] - j0[k, 0, 1], -v0[k, :, 2].min()]
                for k, st in enumerate(states)
            ]
        )
        # Express in the LiDAR frame: R_l = R_lw R_w, t_l = R_lw (J0 + t_w) + t_lw - J0.
        T_lw = np.linalg.inv(T_world_from_lidar)
        R_lw, t_lw = T_lw[:3, :3], T_lw[:3, 3]
        J0 = j0[:, 0]
        go_l = np.stack([rotation_to_axis_angle(R_lw @ R) for R in R_w])
        transl_l = (J0 + transl_w) @ R_lw.T + t_lw - J0
        # The posed body is rigidly moved, so transforming the world vertices equals running the
        # model with the LiDAR-frame parameters (up to float32 rounding; a test checks this).
        v_l = (v0 + transl_w[:, None]) @ R_lw.T + t_lw
        j_l = (j0 + transl_w[:, None]) @ R_lw.T + t_lw
        return states, betas.numpy(), go_l, body_pose, transl_l, v_l, j_l

    def vertex_velocity_base(self, index: int) -> np.ndarray:
        """(K, V, 3) float32 m/s: the velocity of every body vertex of frame ``index`` in the world
        (the robot's motion is not in it), expressed in the base axes of that frame. The people are
        posed at t -+ VERTEX_VELOCITY_STEP_S and differenced (same topology, same vertex order);
        one-sided for a person who starts or stops walking within the step (the pose switches
        between standing and gait there, e.g. walkers starting at t = 0): the side that walks or
        stands as the person does at t."""
        h, t_s = VERTEX_VELOCITY_STEP_S, index / self.options.frame_rate_hz
        times = (t_s - h, t_s, t_s + h)
        world = [
            self._pose_people(t, np.eye(4)) for t in (times[0], times[2])
        ]  # lidar frame = world
        if world[0] is None:
            return np.zeros((0, len(self.model.v_template), 3), np.float32)
        v_world = (world[1][5] - world[0][5]) / (2.0 * h)
        moving = np.array(
            [[pedestrian_state(p, t).moving for t in times] for p in self.scene.pedestrians]
        )
        before, after = moving[:, 0] != moving[:, 1], moving[:, 2] != moving[:, 1]
        if before.any() or after.any():
            here = self._pose_people(t_s, np.eye(4))[5]
            v_world[after] = (here[after] - world[0][5][after]) / h
            v_world[before] = (world[1][5][before] - here[before]) / h
        R_base_from_world = self.robot_pose(index)[0][:3, :3].T
        return (v_world @ R_base_from_world.T).astype(np.float32)

    # ---------------------------------------------------------------- one frame
    def frame(self, index: int) -> SimFrame:
        """Simulate frame ``index`` (0-based)."""
        if not 0 <= index < self.options.frames:
            raise ValueError(f"frame index {index} outside [0, {self.options.frames})")
        t_s = index / self.options.frame_rate_hz
        T_wb, T_wl = self.robot_pose(index)
        posed = self._pose_people(t_s, T_wl)
        st = self._static
        verts, faces = [st["vertices"]], [st["faces"]]
        cls, inst, alb = [st["cls"]], [st["inst"]], [st["albedo"]]
        offset = len(st["vertices"])
        people_world = []
        if posed is not None:
            states, betas, go_l, body_pose, transl_l, v_l, j_l = posed
            for k, spec in enumerate(self.scene.pedestrians):
                vw = transform_points(T_wl, v_l[k].astype(np.float64))
                people_world.append(vw)
                verts.append(vw)
                faces.append(self.person_faces + offset)
                offset += len(vw)
                nf = len(self.person_faces)
                cls.append(np.full(nf, C.PEDESTRIAN, np.uint8))
                inst.append(np.full(nf, spec.track_id, np.uint16))
                hue = np.random.default_rng([self.options.seed, spec.track_id]).uniform(
                    0.15, 0.9, 3
                )
                alb.append(np.broadcast_to(hue.astype(np.float32), (nf, 3)))
        meshes = MeshSet(
            np.concatenate(verts).astype(np.float32),
            np.concatenate(faces).astype(np.uint32),
            np.concatenate(cls),
            np.concatenate(inst),
            np.concatenate(alb),
        )
        rc = meshes.raycasting_scene()
        rng = np.random.default_rng(np.random.SeedSequence([self.options.seed, 0x11DA, index]))
        sweep = cast_lidar(rc, meshes, T_wl, self.options.sensor, self.rig.noise, rng)
        cam0c, cam1c = self.rig.camera("cam0"), self.rig.camera("cam1")
        for c in (cam0c, cam1c):
            if c.name not in self._rays:
                self._rays[c.name] = CameraRays(c)
        cam0 = render_camera(rc, meshes, cam0c, T_wl, self.options.night, self._rays["cam0"])
        cam1 = render_camera(rc, meshes, cam1c, T_wl, self.options.night, self._rays["cam1"])
        occ, occ_inst = self._occupancy(T_wb, people_world)
        people = self._people_gt(posed, T_wb, T_wl, cam0c, cam0)
        people = replace(people, vertex_velocity_base=self.vertex_velocity_base(index))
        T_lw = np.linalg.inv(T_wl)
        objects = []
        for obj in self.scene.objects:
            c = transform_points(T_lw, obj.center[None])[0]
            if np.linalg.norm(c[:2]) <= 40.0:
                yaw = obj.yaw - np.arctan2(T_wl[1, 0], T_wl[0, 0])
                objects.append(ObjectBox(obj, c, float(np.arctan2(np.sin(yaw), np.cos(yaw)))))
        return SimFrame(
            index, t_s, T_wl, T_wb, sweep, cam0, cam1, occ, occ_inst, people, tuple(objects)
        )

    # ---------------------------------------------------------------- ground truth
    def _occupancy(self, T_wb: np.ndarray, people_world: list[np.ndarray]):
        grid = self.grid
        corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
        corners = grid.range_min + corners * (grid.range_max - grid.range_min)
        cw = transform_points(T_wb, corners)
        margin = grid.voxel_size_m
        glo, ghi = cw.min(0) - margin, cw.max(0) + margin
        T_bw = np.linalg.inv(T_wb)
        R_wb, t_wb = T_wb[:3, :3], T_wb[:3, 3]
        static_tris, static_planes = [], []
        for lo, hi, item, solid in self._static["items"]:
            if np.any(hi < glo) or np.any(lo > ghi):
                continue
            verts = item.vertices
            if not solid:  # ground tiles are flat axis-aligned rectangles: clip to the grid
                x0, y0 = np.maximum(lo[:2], glo[:2])
                x1, y1 = np.minimum(hi[:2], ghi[:2])
                verts = np.array(
                    [[x0, y0, lo[2]], [x1, y0, lo[2]], [x1, y1, lo[2]], [x0, y1, lo[2]]]
                )
            vb = transform_points(T_bw, verts)
            static_tris.append((vb, item.faces, item.class_id, not solid))
            if solid:
                n = item.planes[:, :3] @ R_wb
                d = item.planes[:, :3] @ t_wb + item.planes[:, 3]
                static_planes.append(
                    (np.concatenate([n, d[:, None]], axis=1), item.class_id, vb.min(0), vb.max(0))
                )
        people = []
        inside = np.zeros(int(np.prod(grid.shape)), dtype=np.int32)
        centres = grid.centres()
        for spec, vw in zip(self.scene.pedestrians, people_world):
            vb = transform_points(T_bw, vw)
            lo, hi = vb.min(0), vb.max(0)
            if np.any(hi < grid.range_min) or np.any(lo > grid.range_max):
                continue
            people.append((vb, spec.track_id))
            sel = np.flatnonzero(np.all((centres >= lo) & (centres <= hi), axis=1))
            if len(sel):
                sc = o3d.t.geometry.RaycastingScene()
                sc.add_triangles(
                    o3c.Tensor(vb.astype(np.float32)),
                    o3c.Tensor(self.person_faces.astype(np.uint32)),
                )
                occ = sc.compute_occupancy(
                    o3c.Tensor(centres[sel].astype(np.float32)), nsamples=3
                ).numpy()
                inside[sel[occ > 0.5]] = spec.track_id
        inp = G.OccupancyInput(static_tris, static_planes, people, self.person_faces, inside)
        return G.occupancy_grid(inp, grid)

    def _people_gt(self, posed, T_wb, T_wl, cam: object, render: CameraRender) -> PeopleFrame:
        K = len(self.scene.pedestrians)
        if posed is None:
            z = lambda *s: np.zeros((0, *s), np.float32)  # noqa: E731
            return PeopleFrame(
                np.zeros(0, np.int32),
                z(10),
                z(3),
                z(69),
                z(3),
                z(0, 3),
                z(24, 3),
                z(2),
                z(4),
                z(17, 3),
                z(),
                z(3),
                z(3),
                z(),
                (),
            )
        states, betas, go_l, body_pose, transl_l, v_l, j_l = posed
        R_bw = np.linalg.inv(T_wb)[:3, :3]
        T_cl = cam.T_cam_from_lidar
        kp_ids = np.asarray(self.model.keypoint_vertex_ids)
        H, W = render.depth.shape
        box2d = np.full((K, 4), np.nan, np.float32)
        kps = np.zeros((K, 17, 3), np.float32)
        vis = np.zeros(K, np.float32)
        occl = []
        centers, sizes, yaws, vels = [], [], [], []
        robot_yaw = np.arctan2(T_wl[1, 0], T_wl[0, 0])
        for k, (spec, stt) in enumerate(zip(self.scene.pedestrians, states)):
            vl = v_l[k].astype(np.float64)
            vels.append((R_bw @ np.array([stt.velocity[0], stt.velocity[1], 0.0]))[:2])
            yaw = float(
                np.arctan2(np.sin(stt.heading - robot_yaw), np.cos(stt.heading - robot_yaw))
            )
            local = vl @ rot_z(-yaw).T
            lo, hi = local.min(0), local.max(0)
            centers.append(rot_z(yaw) @ ((lo + hi) / 2))
            sizes.append(hi - lo)
            yaws.append(yaw)
            kp_l = np.concatenate([vl[kp_ids], j_l[k][_COCO_JOINT_IDX].astype(np.float64)])
            uv, z = G.project(transform_points(T_cl, kp_l), cam.K)
            flags = G.keypoint_visibility(uv, z, spec.track_id, render.depth, render.instance)
            kps[k, :, :2] = np.where(flags[:, None] > 0, uv, 0.0)
            kps[k, :, 2] = flags
            vc = transform_points(T_cl, vl)
            front = vc[:, 2] > 0.05
            uvv, _ = G.project(vc[front], cam.K)
            in_img = (
                (uvv[:, 0] >= -0.5)
                & (uvv[:, 0] < W - 0.5)
                & (uvv[:, 1] >= -0.5)
                & (uvv[:, 1] < H - 0.5)
            )
            if not in_img.any():
                occl.append("Unknown")
                continue
            x0, y0 = np.clip(uvv.min(0), 0, [W - 1, H - 1])
            x1, y1 = np.clip(uvv.max(0), 0, [W - 1, H - 1])
            box2d[k] = [x0, y0, x1, y1]
            vis[k] = self._visible_fraction(vl, spec.track_id, cam, T_wl, render, box2d[k])
            occl.append(G.occlusion_level(float(vis[k]), True))
        f32 = np.float32
        return PeopleFrame(
            np.array([s.track_id for s in self.scene.pedestrians], np.int32),
            betas.astype(f32),
            go_l.astype(f32),
            body_pose.astype(f32),
            transl_l.astype(f32),
            v_l.astype(f32),
            j_l.astype(f32),
            np.asarray(vels, f32),
            box2d,
            kps,
            vis,
            np.asarray(centers, f32),
            np.asarray(sizes, f32),
            np.asarray(yaws, f32),
            tuple(occl),
        )

    def _visible_fraction(self, verts_lidar, track_id, cam, T_wl, render, box) -> float:
        """Visible / full silhouette pixels of one person in cam, on a pixel lattice in its box."""
        x0, y0, x1, y1 = (int(v) for v in np.rint(box))
        area = (x1 - x0 + 1) * (y1 - y0 + 1)
        step = max(1, int(np.ceil(np.sqrt(area / 40000.0))))
        us, vs = np.meshgrid(np.arange(x0, x1 + 1, step), np.arange(y0, y1 + 1, step))
        us, vs = us.reshape(-1), vs.reshape(-1)
        d = np.stack(
            [(us - cam.K[0, 2]) / cam.K[0, 0], (vs - cam.K[1, 2]) / cam.K[1, 1], np.ones(len(us))],
            1,
        )
        sc = o3d.t.geometry.RaycastingScene()
        vc = transform_points(cam.T_cam_from_lidar, verts_lidar)
        sc.add_triangles(
            o3c.Tensor(vc.astype(np.float32)), o3c.Tensor(self.person_faces.astype(np.uint32))
        )
        rays = np.concatenate([np.zeros_like(d), d], 1).astype(np.float32)
        full = np.isfinite(sc.cast_rays(o3c.Tensor(rays))["t_hit"].numpy())
        if not full.any():
            return 0.0
        seen = render.instance[vs, us] == track_id
        return float(np.count_nonzero(seen & full) / np.count_nonzero(full))

"""Seeded generator of a synthetic campus block: static solids, pedestrians and the robot path.

World frame: z up, the ground at z = 0, the road along +x centred on y = 0 (7.2 m wide), lawns
(terrain) beside it, then trees and buildings. The robot drives along y = 0 at
``robot_speed_mps``. Every class stands inside the benchmark grid (robot-local x 0.4-10 m,
|y| <= 4.8 m) along the way: poles at the kerbs (|y| = 3.7 m), low walls along the outer edge of
the lawns (their faces at |y| = 4.75 m), parked vehicles on the left half of the road with a car,
a delivery truck and a bike right ahead of the start, tree crowns reaching over the lawns.
Instance ids: pedestrians 1..K (their track ids), static things >= 1000, ground 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tasks import conventions as C
from tasks.sim.geometry import (
    Solid,
    Surface,
    box_solid,
    cylinder_solid,
    ellipsoid_solid,
    ground_tile,
)

ROAD_HALF_WIDTH_M = 3.6  # on a 0.2 m voxel boundary, so no voxel straddles road and lawn
#: |y| of the kerb poles (radius 0.08 m: between the road's edge and the lawn walkways)
POLE_Y_M = 3.7
#: the longest half-length (m) of each vehicle kind (_vehicle)
VEHICLE_HALF_LENGTH_M = {"car": 2.4, "truck": 4.0, "two-wheeler": 0.95}
#: |y| of the middle of the low walls (0.3 m thick: their road-side faces at 4.75 m, in the grid)
WALL_Y_M = 4.9
STATIC_INSTANCE_BASE = 1000
SENSORS = ("os1-128", "os1-64", "os1-32")
CROWDS = ("uncrowded", "crowded")


@dataclass(frozen=True)
class SimOptions:
    """What one synthetic sequence looks like.

    seed: everything random derives from it. frames: raw frames at 10 Hz. pedestrians: number of
    people (None: 6 uncrowded, 16 crowded). night: recorded in metadata, darker images.
    sensor: "os1-128" | "os1-64" | "os1-32". robot_speed_mps: forward speed along the road.
    """

    seed: int = 0
    frames: int = 20
    pedestrians: int | None = None
    crowd: str = "uncrowded"
    night: bool = False
    sensor: str = "os1-128"
    robot_speed_mps: float = 1.0
    frame_rate_hz: float = 10.0

    def __post_init__(self):
        if self.crowd not in CROWDS:
            raise ValueError(f"crowd must be one of {CROWDS}, got {self.crowd!r}")
        if self.sensor not in SENSORS:
            raise ValueError(f"sensor must be one of {SENSORS}, got {self.sensor!r}")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.pedestrians is not None and not 0 <= self.pedestrians <= 999:
            raise ValueError(f"pedestrians must be in 0..999, got {self.pedestrians}")

    @property
    def num_pedestrians(self) -> int:
        if self.pedestrians is not None:
            return self.pedestrians
        return 16 if self.crowd == "crowded" else 6


@dataclass(frozen=True)
class LabelledObject:
    """A static thing with a CODa 3D box: center (3,) world m, size (l, w, h) m, yaw rad."""

    instance_id: int
    class_id: int
    class_name: str  # CODa classId, e.g. "Car"
    center: np.ndarray
    size: np.ndarray
    yaw: float


@dataclass(frozen=True)
class PedestrianSpec:
    """One person: behaviour "walk" | "cross" | "stand", start (x, y) world m, heading rad,
    speed m/s, betas (10,) float32, gait phase at t = 0 (cycles), start time s of the motion."""

    track_id: int
    behaviour: str
    start_xy: np.ndarray
    heading: float
    speed_mps: float
    betas: np.ndarray
    phase0: float
    t_start_s: float = 0.0
    t_stop_s: float = 1e9
    gesturing: bool = False


@dataclass(frozen=True)
class Scene:
    """A generated sequence: static geometry, labelled objects, people and the robot path."""

    options: SimOptions
    solids: tuple[Solid, ...]
    surfaces: tuple[Surface, ...]
    objects: tuple[LabelledObject, ...]
    pedestrians: tuple[PedestrianSpec, ...]
    robot_start_xy: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def robot_xy(self, t_s: float) -> np.ndarray:
        """Robot base position (2,) world m at time t_s (seconds since the first frame)."""
        return self.robot_start_xy + np.array([self.options.robot_speed_mps * t_s, 0.0])


def _vehicle(rng, kind: str, x: float, side: int, iid: int):
    """Box-composed vehicle: returns (solids, LabelledObject)."""
    if kind == "car":
        l, w, h, cls, name = (
            rng.uniform(4.0, 4.8),
            rng.uniform(1.7, 1.9),
            rng.uniform(1.4, 1.6),
            C.CAR,
            "Car",
        )
    elif kind == "truck":
        l, w, h = rng.uniform(6.0, 8.0), rng.uniform(2.2, 2.5), rng.uniform(2.8, 3.4)
        cls, name = C.TRUCK, "Delivery Truck"
    else:
        l, w, h, cls, name = rng.uniform(1.7, 1.9), 0.6, 1.1, C.TWO_WHEELER, "Bike"
    # A random kerb gap keeps the sides off voxel faces (the ground truth is exact either way, but a
    # face on a voxel face splits its float32 LiDAR returns between two voxels).
    y = side * (ROAD_HALF_WIDTH_M - rng.uniform(0.2, 0.45) - w / 2)
    yaw = 0.0 if side > 0 else np.pi
    solids = []
    if kind == "car":
        solids.append(box_solid([x, y, 0.25 + 0.45], [l, w, 0.9], yaw, cls, iid))
        solids.append(
            box_solid(
                [x - 0.2 * l * np.cos(yaw), y, 1.15 + (h - 1.15) / 2],
                [0.55 * l, w * 0.9, h - 1.15],
                yaw,
                cls,
                iid,
            )
        )
        for dx in (-0.32 * l, 0.32 * l):
            for dy in (-w / 2 + 0.2, w / 2 - 0.2):
                solids.append(
                    cylinder_solid([x + dx, y + dy, 0.0], 0.22, 0.3, cls, iid, segments=8)
                )
    elif kind == "truck":
        solids.append(
            box_solid(
                [x + 0.35 * l * np.cos(yaw), y, 0.4 + (2.2 - 0.4) / 2],
                [0.3 * l, w, 1.8],
                yaw,
                cls,
                iid,
            )
        )
        solids.append(
            box_solid(
                [x - 0.15 * l * np.cos(yaw), y, 0.5 + (h - 0.5) / 2],
                [0.7 * l, w, h - 0.5],
                yaw,
                cls,
                iid,
            )
        )
        solids.append(box_solid([x, y, 0.25], [0.9 * l, w * 0.9, 0.5], yaw, cls, iid))
    else:
        solids.append(box_solid([x, y, 0.7], [1.2, 0.12, 0.5], yaw, cls, iid))
        for dx in (-0.6, 0.6):
            solids.append(box_solid([x + dx, y, 0.33], [0.66, 0.08, 0.66], yaw, cls, iid))
        solids.append(box_solid([x + 0.5, y, 1.0], [0.1, 0.6, 0.08], yaw, cls, iid))
    center = np.array([x, y, h / 2 if kind != "two-wheeler" else 0.55])
    return solids, LabelledObject(iid, cls, name, center, np.array([l, w, h]), float(yaw))


def build_scene(options: SimOptions) -> Scene:
    """Generate the campus block of one sequence, deterministically from ``options.seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([options.seed, 0x51A]))
    duration = options.frames / options.frame_rate_hz
    x_end = options.robot_speed_mps * duration
    x0, x1 = -40.0, x_end + 60.0
    solids: list[Solid] = []
    surfaces: list[Surface] = []
    objects: list[LabelledObject] = []
    poles: list[tuple[float, float]] = []  # (x, y) world m, kept clear by the people
    next_id = [STATIC_INSTANCE_BASE]

    def new_id() -> int:
        next_id[0] += 1
        return next_id[0] - 1

    # Ground: road tiles in the middle, lawns beside (flat, z = 0), 8 m tiles along x.
    xs = np.arange(x0, x1 + 8.0, 8.0)
    for a, b in zip(xs[:-1], xs[1:]):
        surfaces.append(ground_tile(a, b, -ROAD_HALF_WIDTH_M, ROAD_HALF_WIDTH_M, 0.0, C.ROAD))
        surfaces.append(ground_tile(a, b, ROAD_HALF_WIDTH_M, 30.0, 0.0, C.TERRAIN))
        surfaces.append(ground_tile(a, b, -30.0, -ROAD_HALF_WIDTH_M, 0.0, C.TERRAIN))

    for side in (-1, 1):
        # Buildings (other-structure) with gaps, set back from the road.
        x = x0 + rng.uniform(0, 6)
        while x < x1:
            length = rng.uniform(10, 25)
            depth = rng.uniform(8, 15)
            height = rng.uniform(6, 15)
            setback = rng.uniform(11, 15)
            solids.append(
                box_solid(
                    [x + length / 2, side * (setback + depth / 2), height / 2],
                    [length, depth, height],
                    0.0,
                    C.OTHER_STRUCTURE,
                    new_id(),
                )
            )
            x += length + rng.uniform(3, 10)
        # Low walls along the outer edge of the lawns, with openings.
        x = x0
        while x < x1:
            length = rng.uniform(4, 12)
            if rng.random() < 0.6:
                height = rng.uniform(0.6, 1.2)
                solids.append(
                    box_solid(
                        [x + length / 2, side * WALL_Y_M, height / 2],
                        [length, 0.3, height],
                        0.0,
                        C.OTHER_STRUCTURE,
                        new_id(),
                    )
                )
            x += length + rng.uniform(1, 4)
        # Poles (street lights, signs) at the kerb, one within a few metres ahead of the start.
        xs = [rng.uniform(1.0, 6.0)]
        while xs[0] > x0:
            xs.insert(0, xs[0] - rng.uniform(9, 15))
        while xs[-1] < x1:
            xs.append(xs[-1] + rng.uniform(9, 15))
        for x in xs[1:-1]:
            solids.append(
                cylinder_solid(
                    [x, side * POLE_Y_M, 0.0],
                    0.08,
                    rng.uniform(3.5, 5.0),
                    C.POLE,
                    new_id(),
                    segments=8,
                )
            )
            poles.append((x, side * POLE_Y_M))
        # Trees behind the walls: trunk and crown share the vegetation class and an instance.
        x = x0 + rng.uniform(0, 6)
        while x < x1:
            iid = new_id()
            y = side * rng.uniform(5.4, 6.0)  # behind the walls, crowns over the lawns
            trunk_h = rng.uniform(1.8, 2.6)
            solids.append(
                cylinder_solid(
                    [x, y, 0.0],
                    rng.uniform(0.12, 0.2),
                    trunk_h + 0.5,
                    C.VEGETATION,
                    iid,
                    segments=8,
                )
            )
            r = rng.uniform(1.2, 2.0)
            solids.append(
                ellipsoid_solid([x, y, trunk_h + r * 0.8], [r, r, r * 0.9], C.VEGETATION, iid)
            )
            x += rng.uniform(6, 12)
        # Parked vehicles along the left road edge (the right half of the road and the lawn
        # strips are the walkways). Right ahead of the start one of each kind, close together in
        # random order (every vehicle class in the benchmark grid); random ones before and after.
        if side > 0:
            group: list[tuple[list[Solid], LabelledObject]] = []
            x = rng.uniform(-1.0, 2.0)
            for kind in (str(k) for k in rng.permutation(list(VEHICLE_HALF_LENGTH_M))):
                if group:  # just behind the previous one (its longest half-length ahead)
                    prev = group[-1][1]
                    x = prev.center[0] + prev.size[0] / 2 + rng.uniform(1.0, 2.5)
                    x += VEHICLE_HALF_LENGTH_M[kind]
                group.append(_vehicle(rng, kind, x, side, new_id()))
            rear = min(o.center[0] - o.size[0] / 2 for _, o in group)
            front = max(o.center[0] + o.size[0] / 2 for _, o in group)
            x = x0 + rng.uniform(0, 8)
            while x < x1:
                if rear - 1.0 <= x <= front + 1.0:
                    for parts, obj in group:
                        solids.extend(parts)
                        objects.append(obj)
                    x = front + rng.uniform(3.0, 14.0) + max(VEHICLE_HALF_LENGTH_M.values())
                    rear = np.inf
                    continue
                kind = str(rng.choice(["car", "car", "car", "truck", "two-wheeler"]))
                parts, obj = _vehicle(rng, kind, x, side, new_id())
                if obj.center[0] + obj.size[0] / 2 > rear - 1.0 and np.isfinite(rear):
                    x = rear - 1.0  # would touch the group: place the group next
                    continue
                solids.extend(parts)
                objects.append(obj)
                x += obj.size[0] + rng.uniform(3.0, 14.0)

    peds = _pedestrians(rng, options, duration, objects, poles)
    return Scene(options, tuple(solids), tuple(surfaces), tuple(objects), tuple(peds))


#: Walkways (y ranges of a person's centre, world m): the right half of the road (clear of the
#: robot's line and of the kerb poles) and the lawn strips between the kerb poles and the walls,
#: inside the benchmark grid's |y| <= 4.8.
WALKWAYS = ((-3.25, -0.8), (-4.45, -4.15), (4.15, 4.45))
#: distance (m) a person's centre keeps from a pole's axis
POLE_CLEARANCE_M = 0.45


def _in_vehicle(x: float, y: float, objects, margin: float = 0.6, poles=()) -> bool:
    """(x, y) within margin of a parked vehicle, or within POLE_CLEARANCE_M of a pole."""
    return any(
        abs(x - o.center[0]) < o.size[0] / 2 + margin
        and abs(y - o.center[1]) < o.size[1] / 2 + margin
        for o in objects
    ) or any(np.hypot(x - px, y - py) < POLE_CLEARANCE_M for px, py in poles)


def _pedestrians(
    rng: np.random.Generator,
    options: SimOptions,
    duration: float,
    objects: list[LabelledObject],
    poles: list[tuple[float, float]] = (),
) -> list[PedestrianSpec]:
    """People mostly ahead of the robot (within ~10 m) and in the camera view, on the walkways;
    crossings and standing spots avoid the parked vehicles and the poles, and a new person whose
    path comes within MIN_GAP_M of an earlier one's (or within POLE_CLEARANCE_M of a pole) at
    some time is redrawn (up to 30 times)."""
    times = np.arange(0.0, duration + 0.25, 0.25)
    out: list[PedestrianSpec] = []
    tracks: list[np.ndarray] = []
    pole_xy = np.asarray(poles, dtype=np.float64).reshape(-1, 2)
    for k in range(options.num_pedestrians):
        for _ in range(30):
            spec = _draw_pedestrian(rng, k + 1, options, duration, objects, poles)
            track = _track(spec, times)
            clear_of_poles = (
                not len(pole_xy)
                or np.min(np.linalg.norm(track[:, None, :] - pole_xy[None], axis=2))
                >= POLE_CLEARANCE_M
            )
            if clear_of_poles and all(
                np.min(np.linalg.norm(track - other, axis=1)) >= MIN_GAP_M for other in tracks
            ):
                break
        out.append(spec)
        tracks.append(track)
    return out


MIN_GAP_M = 0.8  # pelvis-to-pelvis distance that keeps two bodies apart


def _track(spec: PedestrianSpec, times: np.ndarray) -> np.ndarray:
    """(T, 2) world xy of a person at ``times`` (vectorised pedestrian_state)."""
    if spec.behaviour == "stand":
        return np.broadcast_to(spec.start_xy, (len(times), 2))
    t_move = np.clip(times, spec.t_start_s, spec.t_stop_s) - spec.t_start_s
    direction = np.array([np.cos(spec.heading), np.sin(spec.heading)])
    return spec.start_xy + (spec.speed_mps * t_move)[:, None] * direction


def _draw_pedestrian(
    rng: np.random.Generator,
    track_id: int,
    options: SimOptions,
    duration: float,
    objects: list[LabelledObject],
    poles: list[tuple[float, float]] = (),
) -> PedestrianSpec:
    v_robot = options.robot_speed_mps
    betas = np.clip(rng.normal(0.0, 0.8, 10), -2.0, 2.0).astype(np.float32)
    kind = rng.choice(["walk_with", "walk_against", "cross", "stand"], p=[0.35, 0.2, 0.25, 0.2])
    phase0 = float(rng.uniform(0, 1))
    w = WALKWAYS[int(rng.choice(len(WALKWAYS), p=[0.6, 0.2, 0.2]))]
    lane = rng.uniform(*w)
    if kind == "walk_with":
        speed = v_robot + rng.uniform(-0.15, 0.35)
        start = [rng.uniform(2.5, 9.0), lane]
        return PedestrianSpec(track_id, "walk", np.array(start), 0.0, float(speed), betas, phase0)
    if kind == "walk_against":
        speed = rng.uniform(0.9, 1.4)
        start = [
            rng.uniform(6.0, 10.0) + (v_robot + speed) * duration * rng.uniform(0.3, 0.7),
            lane,
        ]
        return PedestrianSpec(track_id, "walk", np.array(start), np.pi, float(speed), betas, phase0)
    if kind == "cross":
        speed = rng.uniform(1.0, 1.4)
        side = rng.choice([-1, 1])
        y0 = side * rng.uniform(3.0, 5.0)
        t_start = rng.uniform(0.0, max(0.1, 0.5 * duration))
        # It is on the robot's line 4-8 m ahead of the robot.
        t_mid = t_start + abs(y0) / speed
        x = v_robot * t_mid + rng.uniform(4.0, 8.0)
        for _ in range(20):  # cross in a gap between parked vehicles
            if not any(_in_vehicle(x, y, objects, poles=poles) for y in np.linspace(-5, 5, 21)):
                break
            x += rng.uniform(0.5, 2.0)
        return PedestrianSpec(
            track_id,
            "cross",
            np.array([x, y0]),
            float(-side * np.pi / 2),
            float(speed),
            betas,
            phase0,
            float(t_start),
            float(t_start + 2 * abs(y0) / speed),
        )
    start = [rng.uniform(3.0, 9.0) + v_robot * duration * rng.uniform(0, 0.8), lane]
    for _ in range(20):
        if not _in_vehicle(start[0], start[1], objects, poles=poles):
            break
        start[0] += rng.uniform(0.5, 2.0)
    heading = float(rng.uniform(-np.pi, np.pi))
    return PedestrianSpec(
        track_id,
        "stand",
        np.array(start),
        heading,
        0.0,
        betas,
        phase0,
        gesturing=bool(rng.random() < 0.5),
    )


@dataclass(frozen=True)
class PedestrianState:
    """Where a person is at one instant: xy (2,) world m, heading rad, velocity (2,) world m/s,
    moving (bool: gait vs. standing pose), gait phase (cycles)."""

    track_id: int
    xy: np.ndarray
    heading: float
    velocity: np.ndarray
    moving: bool
    phase: float


STRIDE_CYCLE_M = 1.4  # metres walked per gait cycle (two steps)


def pedestrian_state(spec: PedestrianSpec, t_s: float) -> PedestrianState:
    """The person's state at time t_s (seconds since the first frame)."""
    direction = np.array([np.cos(spec.heading), np.sin(spec.heading)])
    if spec.behaviour == "stand":
        return PedestrianState(
            spec.track_id,
            spec.start_xy.copy(),
            spec.heading,
            np.zeros(2),
            False,
            spec.phase0 + 0.25 * t_s,
        )
    t_move = float(np.clip(t_s, spec.t_start_s, spec.t_stop_s)) - spec.t_start_s
    moving = spec.t_start_s <= t_s <= spec.t_stop_s
    dist = spec.speed_mps * t_move
    xy = spec.start_xy + direction * dist
    vel = direction * spec.speed_mps if moving else np.zeros(2)
    return PedestrianState(
        spec.track_id, xy, spec.heading, vel, moving, spec.phase0 + dist / STRIDE_CYCLE_M
    )

"""Fitted bodies along their tracks: the posed meshes of a frame and each vertex's velocity.

A track's fits share one mesh topology (SMPL's), so every vertex has a trajectory over the frames
where the person was fitted. The velocity of a vertex in frame t is the central difference of its
world positions in the track's previous and next fitted frames (robot motion removed, then
expressed in the base axes of frame t; :func:`tasks.track.velocity.vertex_velocities_in_base`);
one-sided at a track's ends. A neighbour farther than ``max_gap_s`` away does not count (the fit
there is missing or was dropped: a difference over a long gap would blur a swinging limb into its
mean); with neither neighbour, every vertex takes the person's own velocity.

``relative=True`` (fuse.velocity "articulated"): a vertex's velocity is the person's (the
tracker's, as fuse.velocity "person" gives every voxel) plus the vertex's velocity relative to the
body's root (the pelvis joint), both differences taken as above: the torso then moves nearly with
the person, a swinging leg keeps its swing, and the fits' frame-to-frame jitter of the whole body
(root translation) drops out.

``neighbours=k`` > 1 (fuse.velocity_neighbours): the derivative takes up to k fits on each side
(each within ``max_gap_s`` of the next): the slope of the polynomial through them, which follows
a swinging limb closer than the central difference at 5 Hz.
"""

from __future__ import annotations

import numpy as np

from tasks.body.posing import posed_vertices_and_root
from tasks.track.velocity import track_neighbours, vertex_velocities_in_base


class TrackedBodies:
    """The fitted bodies of one sequence, posed frame by frame with per-vertex velocities.

    model: the body model (tasks.body.model.BodyModel). betas (R, 10), global_orient (R, 3),
    body_pose (R, 69), transl (R, 3): the fits, each in the LiDAR frame of its own frame;
    track_id (R,) int; position (R,) int: each row's frame position in the sequence (index into
    stamps_s (F,) seconds and T_world_from_lidar (F, 4, 4)); velocity_base (R, 2) m/s: the
    person's velocity (the fallback). T_base_from_lidar (4, 4).

    Frames are best asked for in order: the rows posed for one frame (its own and its neighbours')
    are kept for the next, so each row is posed about once.
    """

    def __init__(
        self,
        model,
        betas,
        global_orient,
        body_pose,
        transl,
        track_id,
        position,
        velocity_base,
        stamps_s,
        T_world_from_lidar,
        T_base_from_lidar,
        max_gap_s: float,
        relative: bool = False,
        neighbours: int = 1,
    ):
        self.model = model
        self.params = tuple(
            np.asarray(a, np.float32) for a in (betas, global_orient, body_pose, transl)
        )
        self.track_id = np.asarray(track_id, np.int64).reshape(-1)
        self.position = np.asarray(position, np.int64).reshape(-1)
        self.velocity_base = np.asarray(velocity_base, np.float64).reshape(-1, 2)
        self.stamps_s = np.asarray(stamps_s, np.float64).reshape(-1)
        self.T_world_from_lidar = np.asarray(T_world_from_lidar, np.float64).reshape(-1, 4, 4)
        self.T_base_from_lidar = np.asarray(T_base_from_lidar, np.float64)
        self.prev, self.next = track_neighbours(
            self.track_id, self.stamps_s[self.position], max_gap_s
        )
        self.relative = bool(relative)
        # the k-th neighbours on each side (each step within max_gap_s)
        self.sides = [[self.prev], [self.next]]
        for _ in range(max(1, int(neighbours)) - 1):
            for side, link in zip(self.sides, (self.prev, self.next)):
                last = side[-1]
                side.append(np.where(last >= 0, link[np.maximum(last, 0)], -1))
        self._posed: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _pose(self, rows: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """(vertices (V, 3) float32, pelvis (1, 3)) of each row (LiDAR frame of its frame),
        reusing the last call's."""
        todo = np.array([r for r in rows if r not in self._posed], np.int64)
        got = {int(r): self._posed[int(r)] for r in rows if r in self._posed}
        if len(todo):
            verts, roots = posed_vertices_and_root(self.model, *(p[todo] for p in self.params))
            got.update({int(r): (v, j) for r, v, j in zip(todo, verts, roots)})
        self._posed = got
        return got

    def frame(self, position: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bodies of frame ``position``: (rows (K,) int64 into the fits, vertices (K, V, 3)
        float32 LiDAR frame, vertex velocities (K, V, 3) float64 m/s base axes)."""
        rows = np.flatnonzero(self.position == position)
        near = np.concatenate([a[rows] for side in self.sides for a in side])
        posed = self._pose(np.unique(np.concatenate([rows, near[near >= 0]])))
        nv = self.model.v_template.shape[0]
        verts = (
            np.stack([posed[int(r)][0] for r in rows])
            if len(rows)
            else np.zeros((0, nv, 3), np.float32)
        )
        vel = np.zeros((len(rows), nv, 3))
        for k, r in enumerate(rows):
            trio = [a[r] for a in self.sides[0][::-1]] + [r] + [a[r] for a in self.sides[1]]
            at = [self.position[q] if q >= 0 else position for q in trio]
            person = np.r_[self.velocity_base[r], 0.0]

            def diff(part, q=trio, at=at, person=person):
                return vertex_velocities_in_base(
                    [posed[int(x)][part] if x >= 0 else None for x in q],
                    self.T_world_from_lidar[at],
                    self.stamps_s[at],
                    self.T_base_from_lidar,
                    person,
                )

            vel[k] = diff(0)
            if self.relative:  # the person's velocity + the motion relative to the pelvis
                vel[k] += person - diff(1)
        return rows, verts, vel

"""A TF tree as plain data: static edges (``/tf_static``) and stamped edges (``/tf``).

Each edge is ``T_parent_from_child`` (a ``geometry_msgs/TransformStamped`` with header.frame_id
the parent and child_frame_id the child). A frame has at most one parent, as in tf2. A lookup
walks both frames up to their common ancestor; a stamped edge on the way is interpolated at the
query stamp (tasks.poses.interpolate). No file, no clock: the reader hands the edges in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tasks.poses.interpolate import interpolate_poses
from tasks.poses.rotations import invert, transform


class TFGap(ValueError):
    """Two frames are not connected by the tree (or a stamped edge has no value at the stamp)."""


@dataclass(frozen=True)
class StampedEdge:
    """One parent -> child edge over time: stamps_ns (M,) int64 increasing, translations (M, 3),
    quats_wxyz (M, 4)."""

    parent: str
    stamps_ns: np.ndarray
    translations: np.ndarray
    quats_wxyz: np.ndarray


@dataclass(frozen=True)
class TFTree:
    """static: child -> (parent, T_parent_from_child (4, 4)); stamped: child -> StampedEdge."""

    static: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    stamped: dict[str, StampedEdge] = field(default_factory=dict)

    def parent(self, frame: str) -> str | None:
        if frame in self.static:
            return self.static[frame][0]
        if frame in self.stamped:
            return self.stamped[frame].parent
        return None

    def frames(self) -> set[str]:
        out = set(self.static) | set(self.stamped)
        out |= {p for p, _ in self.static.values()} | {e.parent for e in self.stamped.values()}
        return out

    def chain(self, frame: str) -> list[str]:
        """frame, its parent, ... up to its root (a cycle is cut where it closes)."""
        out = [frame]
        while (p := self.parent(out[-1])) is not None and p not in out:
            out.append(p)
        return out

    def is_static_path(self, target: str, source: str) -> bool:
        """Whether the path between the frames uses static edges only (False if not connected)."""
        try:
            up, down = self._path(target, source)
        except TFGap:
            return False
        return all(f in self.static for f in up + down)

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """(children walked up from source, children walked up from target) to the common
        ancestor."""
        src, tgt = self.chain(source), self.chain(target)
        common = next((f for f in src if f in tgt), None)
        if common is None:
            raise TFGap(
                f"no TF path from {source!r} to {target!r}: {source!r} goes up to "
                f"{' -> '.join(src)}, {target!r} goes up to {' -> '.join(tgt)} (no common frame)"
            )
        return src[: src.index(common)], tgt[: tgt.index(common)]

    def lookup(self, target: str, source: str, stamps_ns=None, max_gap_ns=None) -> np.ndarray:
        """T_target_from_source: (4, 4) float64 without stamps (static path only), else (Q, 4, 4)
        at ``stamps_ns`` (Q,). TFGap names the frames (and the first stamp a stamped edge has no
        value at)."""
        up, down = self._path(target, source)
        if stamps_ns is None:
            moving = [f for f in up + down if f not in self.static]
            if moving:
                raise TFGap(
                    f"the path from {source!r} to {target!r} has stamped (/tf) edges "
                    f"({', '.join(moving)}); expected static transforms only"
                )
            T = np.eye(4)
            for f in up:  # T_common_from_source = T_p1_from_... composed upwards
                T = self.static[f][1] @ T
            U = np.eye(4)
            for f in down:
                U = self.static[f][1] @ U
            return invert(U) @ T
        stamps = np.asarray(stamps_ns, np.int64)
        T = np.tile(np.eye(4), (len(stamps), 1, 1))
        U = np.tile(np.eye(4), (len(stamps), 1, 1))
        for chain, acc in ((up, T), (down, U)):
            for f in chain:
                acc[:] = self._edge(f, stamps, max_gap_ns) @ acc
        return np.linalg.inv(U) @ T if down else T

    def _edge(self, child: str, stamps: np.ndarray, max_gap_ns) -> np.ndarray:
        if child in self.static:
            return np.broadcast_to(self.static[child][1], (len(stamps), 4, 4))
        e = self.stamped[child]
        poses, valid = interpolate_poses(
            e.stamps_ns, e.translations, e.quats_wxyz, stamps, max_gap_ns
        )
        if not valid.all():
            k = int(np.flatnonzero(~valid)[0])
            first, last = (
                (int(e.stamps_ns[0]), int(e.stamps_ns[-1])) if len(e.stamps_ns) else (0, 0)
            )
            raise TFGap(
                f"/tf {e.parent!r} -> {child!r} has no value at stamp {int(stamps[k])} ns "
                f"(its {len(e.stamps_ns)} samples span {first}..{last} ns"
                + (f", gaps up to {max_gap_ns} ns bridged" if max_gap_ns is not None else "")
                + ")"
            )
        return poses


def static_edge(parent: str, t, q_wxyz) -> tuple[str, np.ndarray]:
    """A static edge value: (parent, T_parent_from_child) from a translation and a quaternion."""
    return parent, transform(np.asarray(q_wxyz, np.float64), np.asarray(t, np.float64))

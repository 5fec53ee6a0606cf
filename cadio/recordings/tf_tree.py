"""A recording's transform tree (ROS's tf): static and timed edges, looked up at a time.

Each frame has one parent; an edge holds either a static transform (ROS's ``/tf_static``, true at
every time) or a time series (``/tf``, Foxglove's FrameTransform). A lookup at time t walks from
a frame up to the tree's root (or to a fixed frame the caller names) and composes the edges, each
taken at t: interpolated between the samples on either side (linear in translation, spherical
in rotation), a sample itself when t is one, and the nearest sample when t lies before the first
or after the last (the lookup reports how far that was, ``gap_ns``). Frames are strings as
recorded; a leading "/" (ROS 1 habit) is dropped.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from cadio.recordings.recording import TransformMsg
from cadio.records import FloatArray

# Roots whose Z axis is up (REP 105 world-fixed frames, and a robot's base per REP 103): a pose
# looked up from one of them carries gravity (-Z). A camera's own tree (RealSense's
# ``camera_link``) does not: its root is only as level as the camera was mounted.
LEVEL_ROOTS = frozenset({"world", "map", "odom", "earth", "base_link", "base_footprint"})
_MAX_DEPTH = 64  # longer chains are cycles


def frame_name(frame_id: str) -> str:
    """A frame id as the tree keys it."""
    return frame_id.lstrip("/")


def _matrix(t: TransformMsg) -> FloatArray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(t.rotation).as_matrix()
    m[:3, 3] = t.translation
    return m


@dataclass
class _Edge:
    parent: str
    static: FloatArray | None = None
    stamps: list[int] = field(default_factory=list)
    samples: list[TransformMsg] = field(default_factory=list)

    def at(self, stamp_ns: int) -> tuple[FloatArray, int]:
        """(4, 4) child -> parent at ``stamp_ns`` and the distance to the samples used, ns."""
        if self.static is not None:
            return self.static, 0
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if i < len(self.stamps) and self.stamps[i] == stamp_ns:
            return _matrix(self.samples[i]), 0
        if i == 0:
            return _matrix(self.samples[0]), self.stamps[0] - stamp_ns
        if i == len(self.stamps):
            return _matrix(self.samples[-1]), stamp_ns - self.stamps[-1]
        return self._between(i, stamp_ns), 0

    def _between(self, i: int, stamp_ns: int) -> FloatArray:
        a, b = self.samples[i - 1], self.samples[i]
        w = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        m = np.eye(4)
        m[:3, 3] = (1 - w) * np.asarray(a.translation) + w * np.asarray(b.translation)
        slerp = Slerp([0.0, 1.0], Rotation.from_quat([a.rotation, b.rotation]))
        m[:3, :3] = slerp([w]).as_matrix()[0]
        return m


@dataclass(frozen=True)
class Lookup:
    """A frame's pose in ``root``: ``matrix`` (4, 4) maps the frame's coordinates to the
    root's (metres); ``gap_ns`` is the largest distance from the lookup time to a sample that
    had to stand in for it (0 when every edge was static, sampled or interpolated)."""

    matrix: FloatArray
    root: str
    gap_ns: int


class TransformTree:
    """Transforms added as a recording streams by, looked up by frame and time."""

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}  # child frame -> its edge

    def __bool__(self) -> bool:
        return bool(self._edges)

    def add(self, t: TransformMsg) -> None:
        """Add one transform; a frame that changes parent keeps only its new edge."""
        child, parent = frame_name(t.child), frame_name(t.parent)
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent:
            edge = self._edges[child] = _Edge(parent)
        if t.static:
            edge.static = _matrix(t)
            return
        i = bisect.bisect_right(edge.stamps, t.stamp_ns)
        edge.stamps.insert(i, t.stamp_ns)
        edge.samples.insert(i, t)

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root, in that order."""
        out = [frame_name(frame)]
        while out[-1] in self._edges and len(out) <= _MAX_DEPTH:
            parent = self._edges[out[-1]].parent
            if parent in out:
                break  # a cycle: the recording is inconsistent; stop at the repeat
            out.append(parent)
        return out

    def lookup(self, frame: str, stamp_ns: int, fixed: str | None = None) -> Lookup | None:
        """``frame``'s pose at ``stamp_ns`` in ``fixed`` (None: the root of its tree); None
        when no edge leads from ``frame`` or ``fixed`` lies in another tree."""
        up = self.chain(frame)
        if len(up) == 1:
            return None
        pose, gap = self._compose(up, stamp_ns)
        root = up[-1]
        if fixed is None or frame_name(fixed) == root:
            return Lookup(pose, root, gap)
        fixed_up = self.chain(fixed)
        if fixed_up[-1] != root:
            return None
        fixed_pose, fixed_gap = self._compose(fixed_up, stamp_ns)
        return Lookup(np.linalg.inv(fixed_pose) @ pose, frame_name(fixed), max(gap, fixed_gap))

    def between(self, target: str, source: str, stamp_ns: int) -> FloatArray | None:
        """(4, 4) mapping ``source`` coordinates to ``target``'s at ``stamp_ns``, through their
        common root; None when they lie in different trees (or either has no edge)."""
        a, b = self.lookup(target, stamp_ns), self.lookup(source, stamp_ns)
        if a is None or b is None or a.root != b.root:
            return None
        return np.asarray(np.linalg.inv(a.matrix) @ b.matrix, dtype=np.float64)

    def _compose(self, up: list[str], stamp_ns: int) -> tuple[FloatArray, int]:
        pose, gap = np.eye(4), 0
        for child in up[:-1]:
            edge, edge_gap = self._edges[child].at(stamp_ns)
            pose, gap = edge @ pose, max(gap, edge_gap)
        return pose, gap

    def prune(self, horizon_ns: int) -> None:
        """Forget timed samples before ``horizon_ns``, keeping the last one before it (a later
        lookup may still need to interpolate from it)."""
        for edge in self._edges.values():
            i = bisect.bisect_left(edge.stamps, horizon_ns) - 1
            if i > 0:
                del edge.stamps[:i], edge.samples[:i]

"""From a recording's messages to RGB-D frames: pairing by time, calibration, pose, colour.

Both MCAP dialects end here (``cadio.recordings.recording``'s records), so the rules are one:

- **Pairing**: each depth image is paired with the nearest colour image (and instance image)
  within a tolerance (a frame period: colour and depth come from different sensors, stamped
  apart); a depth image is settled once the stream has moved a tolerance past it (no nearer
  partner can arrive) or at the end. Depth without colour within it is kept without colour
  (the geometry needs the depth, not the colour), and the reader warns.
- **Calibration**: an image's camera info is, among the latest message of each camera info
  topic when the image settles, one of the image's size, preferring the same frame id, then the
  topic sharing the longest namespace (``/camera/color/camera_info`` for
  ``/camera/color/image_raw``). Drivers publish camera info with every image, unchanged; a
  depth image with none of its size waits for one (and the reader fails at the end without).
- **Pose**: the chain of the transform tree from its root (or a named fixed frame) to the depth
  image's frame id, at the depth image's stamp (``cadio.recordings.tf_tree``).
- **Colour**: taken as is when it is registered to depth (same size and intrinsics); else
  re-projected into the depth camera through the transform between the two frames the recording
  holds (each depth pixel's point, moved into the colour camera, takes the colour of the nearest
  pixel it lands on; no occlusion test); else left out of the frame (black) with a warning.
- **Gravity** (``levelling``): when the pose does not come from a level root, the dominant plane
  of the first frame (the table or floor under the parts) is taken as horizontal, and the world
  is rotated so that its Z axis is that plane's normal, pointing at the camera.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from cadio.recordings.recording import CalibrationMsg, ImageMsg
from cadio.recordings.tf_tree import TransformTree, frame_name
from cadio.records import CameraIntrinsics, FloatArray

log = logging.getLogger(__name__)

MIN_SUPPORT_SHARE = 0.2  # the support plane holds at least this share of a frame's depth points


@dataclass(frozen=True)
class Pair:
    """A settled depth image, its partners and the calibrations that fit them."""

    depth: ImageMsg
    colour: ImageMsg | None  # None: no colour image within the tolerance
    instance: ImageMsg | None
    depth_calibration: CalibrationMsg
    colour_calibration: CalibrationMsg | None


def _namespace_overlap(a: str, b: str) -> int:
    n = 0
    for x, y in zip(a.strip("/").split("/"), b.strip("/").split("/"), strict=False):
        if x != y:
            break
        n += 1
    return n


def calibration_for(img: ImageMsg, calibrations: dict[str, CalibrationMsg]
                    ) -> CalibrationMsg | None:
    """The camera info of an image (see the module docstring); None when none has its size."""
    sized = [c for c in calibrations.values() if (c.width, c.height) == (img.width, img.height)]
    return max(sized, default=None, key=lambda c: (c.frame_id == img.frame_id,
                                                   _namespace_overlap(c.topic, img.topic)))


@dataclass
class Pairer:
    """Streams depth images and settles each with its nearest partners within ``tol`` ns."""

    tol: int
    tree: TransformTree = field(default_factory=TransformTree)
    depth: deque[ImageMsg] = field(default_factory=deque)
    others: dict[str, deque[ImageMsg]] = field(
        default_factory=lambda: {"colour": deque(), "instance": deque()})
    calibrations: dict[str, CalibrationMsg] = field(default_factory=dict)  # latest per topic
    uncoloured: int = 0  # depth images without colour within the tolerance

    def add_image(self, role: str, img: ImageMsg) -> None:
        if role == "depth":
            self.depth.append(img)
            return
        self.others[role].append(img)
        # Without a pending depth image nothing older than a tolerance behind can pair.
        self._prune(self.depth[0].stamp_ns - self.tol if self.depth
                    else img.stamp_ns - 2 * self.tol)

    def add_calibration(self, calibration: CalibrationMsg) -> None:
        self.calibrations[calibration.topic] = calibration

    def _prune(self, horizon: int) -> None:
        for q in self.others.values():
            while q and q[0].stamp_ns < horizon:
                q.popleft()

    def settled(self, now: int | None) -> Iterator[Pair]:
        """Pairs ready at stream time ``now`` (None: the end of the stream, settle all)."""
        while self.depth and (now is None or now > self.depth[0].stamp_ns + self.tol):
            d = self.depth[0]
            calibration = calibration_for(d, self.calibrations)
            if calibration is None:
                return  # it may still come; at the end of the stream the reader says so
            self.depth.popleft()
            colour, instance = self._nearest("colour", d), self._nearest("instance", d)
            self._prune(d.stamp_ns - self.tol)
            self.tree.prune(d.stamp_ns - self.tol)
            if colour is None:
                self.uncoloured += 1
                log.debug("depth at %d ns has no colour within %d ns", d.stamp_ns, self.tol)
            yield Pair(d, colour, instance, calibration,
                       None if colour is None else calibration_for(colour, self.calibrations))

    def _nearest(self, role: str, d: ImageMsg) -> ImageMsg | None:
        cands = [m for m in self.others[role] if abs(m.stamp_ns - d.stamp_ns) <= self.tol]
        return min(cands, key=lambda m: abs(m.stamp_ns - d.stamp_ns), default=None)


def _known_frame(frame_id: str) -> bool:
    """Whether a frame id names a frame: drivers without a tf setup write "" or "0"."""
    name = frame_name(frame_id)
    return bool(name) and not name.isdigit()


def registered(pair: Pair) -> bool:
    """Whether the colour image is registered to the depth image (pixel for pixel)."""
    d, c, cal = pair.depth, pair.colour, pair.colour_calibration
    if c is None or (c.width, c.height) != (d.width, d.height):
        return False
    if cal is None or cal is pair.depth_calibration:
        return True
    a, b = cal.intrinsics(), pair.depth_calibration.intrinsics()
    return bool(np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=1e-6))


def colour_extrinsic(pair: Pair, tree: TransformTree) -> FloatArray | None:
    """(4, 4) depth camera -> colour camera coordinates, when the recording holds it: identity
    for one named frame, else the transform tree's path between the two frames."""
    if pair.colour is None:
        return None
    df, cf = pair.depth.frame_id, pair.colour.frame_id
    if not (_known_frame(df) and _known_frame(cf)):
        return None
    if frame_name(df) == frame_name(cf):
        return np.eye(4)
    return tree.between(cf, df, pair.depth.stamp_ns)


def register_colour(depth: npt.NDArray[np.float32], k_depth: CameraIntrinsics,
                    colour: npt.NDArray[np.uint8], k_colour: CameraIntrinsics,
                    colour_from_depth: FloatArray) -> npt.NDArray[np.uint8]:
    """Colour of each depth pixel: its point moved into the colour camera and projected, the
    nearest colour pixel taken; black where depth is missing or the point falls outside.

    Args:
        depth: (h, w) float32 metres. colour: (hc, wc, 3) uint8.
        colour_from_depth: (4, 4) depth camera -> colour camera coordinates, metres.
    Returns:
        (h, w, 3) uint8.
    """
    out = np.zeros((*depth.shape, 3), dtype=np.uint8)
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u].astype(np.float64)
    pts = np.column_stack([(u - k_depth.cx) / k_depth.fx * z, (v - k_depth.cy) / k_depth.fy * z, z])
    pc = pts @ colour_from_depth[:3, :3].T + colour_from_depth[:3, 3]
    front = pc[:, 2] > 1e-9
    zc = np.where(front, pc[:, 2], 1.0)
    uc = np.round(k_colour.fx * pc[:, 0] / zc + k_colour.cx).astype(np.int64)
    vc = np.round(k_colour.fy * pc[:, 1] / zc + k_colour.cy).astype(np.int64)
    inside = front & (uc >= 0) & (uc < colour.shape[1]) & (vc >= 0) & (vc < colour.shape[0])
    out[v[inside], u[inside]] = colour[vc[inside], uc[inside]]
    return out


def _rotation_to_z(up: FloatArray) -> FloatArray:
    """(3, 3) the smallest rotation taking unit ``up`` to +Z."""
    from scipy.spatial.transform import Rotation

    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = float(np.linalg.norm(axis)), float(np.dot(up, z))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return np.asarray(Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix())


def levelling(depth: npt.NDArray[np.float32], k: CameraIntrinsics,
              camera_to_world: FloatArray) -> tuple[FloatArray, str]:
    """(4, 4) rotation of the world that makes its +Z point up, and how up was found.

    Up is the normal of the frame's support plane (the RANSAC plane of ``cadio.capture.segment``
    holding at least ``MIN_SUPPORT_SHARE`` of the depth points), on the camera's side:
    "support plane". Without such a plane the camera is taken to be upright and level (up is
    the image's up, -y of the optical frame): "level camera".
    """
    from cadio.capture.segment import SegmentConfig, fit_plane

    cfg = SegmentConfig()
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u].astype(np.float64)
    pts = np.column_stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])
    up_camera, source = np.array([0.0, -1.0, 0.0]), "level camera"
    if len(pts) >= 500:
        n, d = fit_plane(pts, cfg)
        share = float(np.mean(np.abs(pts @ n - d) <= cfg.plane_distance_m))
        if share >= MIN_SUPPORT_SHARE:
            up_camera, source = (-n if d > 0 else n), "support plane"  # the camera is at 0
    out = np.eye(4)
    out[:3, :3] = _rotation_to_z(camera_to_world[:3, :3] @ up_camera)
    return out, source

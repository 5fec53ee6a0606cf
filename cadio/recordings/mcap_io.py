"""RGB-D captures in MCAP: read recordings of either dialect back as frames; write our own.

Two dialects carry RGB-D in MCAP, and the reader takes both, channel by channel:

- **Foxglove** (``protobuf``): ``foxglove.RawImage``, ``CameraCalibration``,
  ``FrameTransform(s)``. What this package writes (``cadio.recordings.foxglove_mcap``, whose
  writer is re-exported here) and what Foxglove's SDK logs.
- **ROS 2** (``cdr``): ``sensor_msgs/msg/Image``, ``CompressedImage``, ``CameraInfo``,
  ``tf2_msgs/msg/TFMessage`` on ``/tf`` and ``/tf_static``. What ``ros2 bag record`` writes
  (``cadio.recordings.ros2_mcap``).

What a recording must hold: a depth image topic (16UC1 or mono16 in depth units, 1 mm by
default; 32FC1 in metres), a colour image topic, and camera info of the depth image's size.
What it may hold: the transform tree (the camera's pose: the chain from the tree's root, or from
``fixed_frame``, to the depth image's frame id; without it the camera is the world frame and
every frame says so in ``meta["warnings"]``), camera info for the colour camera and the
transform between the colour and depth frames (colour from another sensor), an instance-id
image, and the scene description (``/scene``, JSON). Topics are found by schema and encoding,
not by name; every topic not used is skipped. The pairing, calibration, pose, colour and
gravity rules are ``cadio.recordings.pairing``'s.

Each frame's ``meta`` says where it came from: ``dialect``, ``depth_topic``, ``colour_topic``,
``colour_offset_ns``, ``colour`` (registered / reprojected / left out), ``pose_source`` (tf /
given / camera), ``world_frame``, ``tf_gap_ns`` (how far the nearest transform stood from the
stamp, when none bracketed it), ``gravity_source`` (tf / given / support plane / level camera)
and ``warnings``. Errors name the file and the topic: ``CaptureTopicError`` (a topic
missing, or holding an unknown schema or encoding) and ``CaptureTruncatedError`` (raised after
the complete frames before the damage).
"""

from __future__ import annotations

import errno
import json
import logging
import struct
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import IO, Any, cast

import numpy as np
import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Schema
from mcap.stream_reader import StreamReader

from cadio.errors import CaptureError, CaptureTopicError, CaptureTruncatedError
from cadio.recordings.channels import EXPECTED, Channels, kind_of, preferred
from cadio.recordings.foxglove_mcap import (
    CAMERA_INFO_TOPIC,
    COLOR_TOPIC,
    DEPTH_M,
    DEPTH_MM,
    DEPTH_TOPIC,
    INSTANCE_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    CaptureWriter,
    depth_to_mm,
    write_capture,
)
from cadio.recordings.pairing import (
    Pair,
    Pairer,
    colour_extrinsic,
    levelling,
    register_colour,
    registered,
)
from cadio.recordings.recording import (
    SIDES,
    CalibrationMsg,
    ImageMsg,
    PixelError,
    Record,
    TransformMsg,
    colour_pixels,
    depth_metres,
    instance_ids,
    intrinsics_problem,
    size_problem,
)
from cadio.recordings.ros2_mcap import ROS2, STRING
from cadio.recordings.tf_tree import LEVEL_ROOTS, Lookup
from cadio.records import FloatArray, RgbdFrame

__all__ = [
    "CAMERA_INFO_TOPIC", "COLOR_TOPIC", "DEPTH_M", "DEPTH_MM", "DEPTH_TOPIC", "INSTANCE_TOPIC",
    "SCENE_TOPIC", "TF_TOPIC", "CaptureWriter", "ReadOptions", "RecordingSummary", "depth_to_mm",
    "read_capture", "read_scene_meta", "summarise_capture", "write_capture",
]

log = logging.getLogger(__name__)

_MAX_PENDING = 300  # depth images held while waiting for a calibration (10 s at 30 fps)
# What a damaged file raises inside the mcap reader: short reads, bad CRCs, bad zstd frames.
_DAMAGE = (McapError, ValueError, struct.error, EOFError, zstandard.ZstdError)


@dataclass(frozen=True, eq=False)
class ReadOptions:
    """How ``read_capture`` reads a recording.

    pose: world_to_camera (4, 4), metres, for frames without a transform (None: the camera is
        the world frame, levelled by the support plane, with a warning).
    tolerance_ns: pairing tolerance (34 ms: a frame period at 30 fps; colour and depth come
        from different sensors and are not stamped together).
    depth_scale_m: metres per unit of 16UC1 / mono16 depth (1 mm, the ROS convention).
    depth_topic, colour_topic: pick topics when a recording has several.
    fixed_frame: the frame poses are given in, taken to be level (None: the root of the depth
        frame's tree, level when it is ``world``, ``map``, ``odom``, ``earth`` or a robot base).
    """

    pose: FloatArray | None = None
    tolerance_ns: int = 34_000_000
    depth_scale_m: float = 0.001
    depth_topic: str | None = None
    colour_topic: str | None = None
    fixed_frame: str | None = None


def _stream(path: Path, fh: IO[bytes]) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) records in file order; damage -> CaptureTruncatedError."""
    count = 0
    try:
        reader = NonSeekingReader(fh, validate_crcs=True)
        for item in reader.iter_messages(log_time_order=False):
            count += 1
            yield item
    except _DAMAGE as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if isinstance(exc, EndOfFile):
            detail = f"the file ends after {fh.tell()} bytes"
        raise CaptureTruncatedError(path, count, detail) from exc


def _summary(fh: IO[bytes]) -> Any:
    """The file's summary (schemas, channels, indexes), or None when missing or damaged."""
    try:
        return SeekingReader(fh).get_summary()
    except _DAMAGE:
        return None  # e.g. truncated: callers scan the stream instead
    except OSError as exc:  # shorter than a footer: the reader seeks before the file's start
        if exc.errno != errno.EINVAL:
            raise
        return None
    finally:
        fh.seek(0)


def _channels(fh: IO[bytes]) -> list[tuple[str, str | None]]:
    """(topic, kind) of every channel: from the summary, or in a file without one (truncated),
    from the records before the damage."""
    summary = _summary(fh)
    if summary is not None:
        return [(c.topic, kind_of(summary.schemas.get(c.schema_id), c))
                for c in summary.channels.values()]
    schemas: dict[int, Schema] = {}
    out = []
    try:
        for record in StreamReader(fh).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                out.append((record.topic, kind_of(schemas.get(record.schema_id), record)))
    except _DAMAGE:
        pass  # the channels registered before the damage are all a reader can use
    finally:
        fh.seek(0)
    return out


class _Reader:
    """One pass over a recording: channels to records, records to pairs, pairs to frames."""

    def __init__(self, path: Path, opts: ReadOptions) -> None:
        self.path, self.opts = path, opts
        self.pairer = Pairer(opts.tolerance_ns)
        self.channels = Channels(path, opts.depth_topic, opts.colour_topic)
        self.warnings: list[str] = []
        self.level: FloatArray | None = None  # the world's rotation to Z up, once decided
        self.gravity = ""
        self.frames_out = 0
        self.empty = 0  # depth images without a measured pixel, skipped

    def frames(self) -> Iterator[RgbdFrame]:
        with self.path.open("rb") as fh:
            aligned, twins = preferred(_channels(fh))
            self.channels.depth_topic = self.opts.depth_topic or aligned
            self.channels.twins = twins
            try:
                for schema, channel, message in _stream(self.path, fh):
                    got = self.channels.records(schema, channel, message)
                    if got is not None:
                        yield from self._add(*got)
                    if len(self.pairer.depth) > _MAX_PENDING:
                        raise self._no_calibration()
            except CaptureError:
                yield from self._emit(None)  # every complete frame before the damage
                raise
        yield from self._emit(None)
        self._finish()

    def _add(self, role: str, records: list[Record]) -> Iterator[RgbdFrame]:
        for r in records:
            if isinstance(r, TransformMsg):
                self.pairer.tree.add(r)
            elif isinstance(r, CalibrationMsg):
                self.pairer.add_calibration(r)
            else:
                self.pairer.add_image(role, r)
                yield from self._emit(r.stamp_ns)

    def _emit(self, now: int | None) -> Iterator[RgbdFrame]:
        for pair in self.pairer.settled(now):
            frame = self._frame(pair)
            if frame is not None:
                self.frames_out += 1
                yield frame

    def _warn(self, message: str) -> None:
        if message not in self.warnings:
            self.warnings.append(message)
            log.warning("%s: %s", self.path, message)

    def _frame(self, pair: Pair) -> RgbdFrame | None:
        """The frame of a pair; None for a depth image without a measured pixel (a sensor
        starting up), which is skipped with a warning."""
        d, k = pair.depth, pair.depth_calibration.intrinsics()
        _check_pair(self.path, pair)
        depth = _pixels(self.path, d, lambda: depth_metres(d, self.opts.depth_scale_m))
        if not np.any(depth > 0):
            self.empty += 1
            self._warn(f"depth images of {d.topic} without a measured pixel are skipped")
            return None
        look = (self.pairer.tree.lookup(d.frame_id, d.stamp_ns, self.opts.fixed_frame)
                if self.pairer.tree else None)
        world_to_camera = self._pose(pair, depth, look)
        if not np.all(np.isfinite(world_to_camera)):
            raise CaptureTopicError(self.path, None, f"the camera pose of the depth image at "
                                    f"{d.stamp_ns} ns is not finite (NaN or infinity in "
                                    f"{'its transforms' if look else 'the pose given'})",
                                    "finite transforms")
        rgb, colour_mode = self._colour(pair, depth)
        inst = pair.instance
        ids = (None if inst is None or (inst.width, inst.height) != (d.width, d.height)
               else _pixels(self.path, inst, lambda: instance_ids(inst)))
        c = pair.colour
        meta = {"dialect": self.channels.dialects.get(d.topic, ""), "depth_topic": d.topic,
                "colour_topic": c.topic if c is not None else "",
                "colour_offset_ns": c.stamp_ns - d.stamp_ns if c is not None else 0,
                "colour": colour_mode,
                "pose_source": "tf" if look else ("given" if self.opts.pose is not None
                                                  else "camera"),
                "world_frame": look.root if look else "", "tf_gap_ns": look.gap_ns if look else 0,
                "gravity_source": self.gravity, "warnings": tuple(self.warnings)}
        return RgbdFrame(timestamp_ns=d.stamp_ns, intrinsics=k, colour=rgb, depth=depth,
                         world_to_camera=world_to_camera, instance=ids, meta=meta)

    def _pose(self, pair: Pair, depth: Any, look: Lookup | None) -> FloatArray:
        """world_to_camera of a frame: the tf chain's, the given pose, or the camera's own
        frame; levelled by the support plane where the tree's root is not level."""
        if look is None and self.opts.pose is not None:
            self.gravity = self.gravity or "given"
            return np.array(self.opts.pose, dtype=np.float64)
        if look is None:
            self._warn(f"no transform chain reaches the depth frame {pair.depth.frame_id!r}: "
                       "the camera is the world frame")
        camera_to_world = look.matrix if look is not None else np.eye(4)
        if not self.gravity:
            self._gravity(pair, depth, look, camera_to_world)
        if self.level is not None:
            camera_to_world = self.level @ camera_to_world
        return np.asarray(np.linalg.inv(camera_to_world), dtype=np.float64)

    def _gravity(self, pair: Pair, depth: Any, look: Lookup | None,
                 camera_to_world: FloatArray) -> None:
        """Decide, once per recording, where up is (see ``cadio.recordings.pairing``)."""
        if look is not None and (look.root in LEVEL_ROOTS or self.opts.fixed_frame):
            self.gravity = "tf"
            return
        k = pair.depth_calibration.intrinsics()
        self.level, self.gravity = levelling(depth, k, camera_to_world)
        if self.gravity == "level camera":
            self._warn("no support plane in the first frame: gravity taken along the image's "
                       "down axis (a level camera)")
        else:
            log.info("%s: gravity from the support plane of the first frame", self.path)

    def _colour(self, pair: Pair, depth: Any) -> tuple[Any, str]:
        c, d, cal = pair.colour, pair.depth, pair.colour_calibration
        if c is None:
            ms = self.opts.tolerance_ns / 1e6
            self._warn(f"depth images of {d.topic} without a colour image within {ms:g} ms "
                       "(the sensors are stamped apart): those frames have no colour")
            return np.zeros((d.height, d.width, 3), dtype=np.uint8), "none"
        if registered(pair):
            return _pixels(self.path, c, lambda: colour_pixels(c)), "registered"
        extrinsic = colour_extrinsic(pair, self.pairer.tree) if cal is not None else None
        if cal is None or extrinsic is None:
            lacks = "camera info for the colour" if cal is None else "transform between them"
            self._warn(f"colour {c.topic} ({c.width}x{c.height}, frame {c.frame_id!r}) is not "
                       f"registered to depth {d.topic} ({d.width}x{d.height}, frame "
                       f"{d.frame_id!r}) and the recording holds no {lacks}: colour left out")
            return np.zeros((d.height, d.width, 3), dtype=np.uint8), "left out"
        rgb = _pixels(self.path, c, lambda: colour_pixels(c))
        return register_colour(depth, pair.depth_calibration.intrinsics(), rgb,
                               cal.intrinsics(), extrinsic), "reprojected"

    def _no_calibration(self) -> CaptureTopicError:
        d = self.pairer.depth[0]
        have = ", ".join(f"{c.topic} ({c.width}x{c.height})"
                         for c in self.pairer.calibrations.values()) or "none"
        return CaptureTopicError(self.path, d.topic, f"no camera info of its size "
                                 f"{d.width}x{d.height} (camera info: {have})",
                                 EXPECTED["calibration"])

    def _finish(self) -> None:
        if self.pairer.depth:
            raise self._no_calibration()
        for role in ("depth", "colour"):
            if getattr(self.channels, f"{role}_topic") is None:
                raise self.channels.missing(role)
        if self.frames_out == 0 and self.empty:
            raise CaptureTopicError(self.path, self.channels.depth_topic, f"all {self.empty} "
                                    "depth images are empty (no pixel with a depth)",
                                    "depth images with measured pixels")


def _check_pair(path: Path, pair: Pair) -> None:
    """Refuse what would crash or mislead the stages downstream: an image of a size no camera
    gives (``recording.size_problem``), camera info that cannot back-project."""
    for img in (pair.depth, *([pair.colour] if pair.colour is not None else [])):
        size = size_problem(img)
        if size is not None:
            raise CaptureTopicError(path, img.topic, f"image of {size}", f"images of {SIDES}")
    for cal in (pair.depth_calibration, pair.colour_calibration):
        bad = None if cal is None else intrinsics_problem(cal.intrinsics())
        if cal is not None and bad is not None:
            raise CaptureTopicError(path, cal.topic, f"camera info with {bad}",
                                    "finite focal lengths above 0 and a finite principal point")


def _pixels(path: Path, img: ImageMsg, decode: Any) -> Any:
    try:
        return decode()
    except PixelError as exc:
        raise CaptureTopicError(path, img.topic, str(exc),
                                f"{img.width}x{img.height} {img.encoding}") from exc


def read_capture(path: Path | str, *, pose: FloatArray | None = None,
                 tolerance_ns: int = ReadOptions.tolerance_ns, depth_scale_m: float = 0.001,
                 depth_topic: str | None = None, colour_topic: str | None = None,
                 fixed_frame: str | None = None) -> Iterator[RgbdFrame]:
    """Yield the RGB-D frames of an MCAP recording: ours, a Foxglove one or a ROS 2 one.

    Args:
        path: the .mcap file.
        pose, tolerance_ns, depth_scale_m, depth_topic, colour_topic, fixed_frame: see
            ``ReadOptions``.
    Yields:
        RgbdFrame with depth (h, w) float32 metres (0 = missing) in the depth camera's
        intrinsics, colour registered to it, instance ids when present, ``meta`` as the module
        docstring says.
    Raises:
        CaptureTopicError: a topic the reader needs is missing, or one holds an unknown schema
            or encoding, or no camera info fits the depth images.
        CaptureTruncatedError: after the last complete frame of a truncated or corrupt file.
    """
    opts = ReadOptions(pose, tolerance_ns, depth_scale_m, depth_topic, colour_topic, fixed_frame)
    return _Reader(Path(path), opts).frames()


def read_scene_meta(path: Path | str) -> dict[str, Any] | None:
    """The JSON scene description on ``/scene``, or None when the capture has none.

    Raises:
        CaptureError: the file is damaged before the scene message, or ``/scene`` does not
            hold JSON (``json``, or a ``std_msgs/msg/String`` in a ROS 2 recording).
    """
    path = Path(path)
    with path.open("rb") as fh:
        summary = _summary(fh)
        if summary is not None and all(c.topic != SCENE_TOPIC for c in summary.channels.values()):
            return None
        for schema, channel, message in _stream(path, fh):
            if channel.topic == SCENE_TOPIC:
                return _scene(path, schema, channel, message)
    return None


def _scene(path: Path, schema: Any, channel: Any, message: Any) -> dict[str, Any]:
    encoding, name = channel.message_encoding, schema.name if schema is not None else ""
    try:
        if encoding == "json":
            return cast(dict[str, Any], json.loads(message.data))
        if encoding == "cdr" and name in (STRING, STRING.replace("/msg/", "/")):
            decoded = ROS2.decoders().decoder_for(encoding, schema)(message.data)
            return cast(dict[str, Any], json.loads(decoded.data))
    except (ValueError, McapError) as exc:
        raise CaptureTopicError(path, SCENE_TOPIC, f"not JSON ({exc})", "a JSON object") from exc
    raise CaptureTopicError(path, SCENE_TOPIC, f"schema {name or 'none'} ({encoding})",
                            f"JSON (json) or {STRING} (cdr) holding JSON")


@dataclass(frozen=True)
class RecordingSummary:
    """What ``read_capture`` made of a recording (``mateqa capture --read``): the frames read,
    their topics, camera, time span and sources, the warnings, and the error that stopped it
    (empty when none)."""

    path: str
    frames: int = 0
    dialect: str = ""
    depth_topic: str = ""
    colour_topic: str = ""
    intrinsics: dict[str, float] = field(default_factory=dict)
    first_ns: int = 0
    last_ns: int = 0
    pose_source: str = ""
    world_frame: str = ""
    gravity_source: str = ""
    colour: tuple[str, ...] = ()
    instance_ids: bool = False
    scene: bool = False
    warnings: tuple[str, ...] = ()
    error: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def summarise_capture(path: Path | str, **options: Any) -> RecordingSummary:
    """Read a recording through (``read_capture``'s ``options``) and say what was read; an
    error is carried in the summary, after the frames read before it."""
    out = RecordingSummary(str(path))
    colour: set[str] = set()
    try:
        for f in read_capture(path, **options):
            m = f.meta
            colour.add(m["colour"])
            out = replace(out, frames=out.frames + 1, dialect=m["dialect"],
                          depth_topic=m["depth_topic"], colour_topic=m["colour_topic"],
                          intrinsics=asdict(f.intrinsics), first_ns=out.first_ns or f.timestamp_ns,
                          last_ns=f.timestamp_ns, pose_source=m["pose_source"],
                          world_frame=m["world_frame"], gravity_source=m["gravity_source"],
                          instance_ids=out.instance_ids or f.instance is not None,
                          warnings=m["warnings"])
        out = replace(out, scene=read_scene_meta(path) is not None)
    except (CaptureError, OSError) as exc:
        out = replace(out, error=str(exc))
    return replace(out, colour=tuple(sorted(colour)))

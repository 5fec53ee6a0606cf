"""RGB-D captures as MCAP files with Foxglove protobuf schemas: write, and read back as frames.

The only module that imports ``mcap``. Files are zstd-chunked, indexed and carry a summary (the
plain ``mcap`` writer with ``foxglove-schemas-protobuf`` message classes), so Foxglove and any
MCAP reader open them. Topics (constants below):

===========================  ==========================  ======================================
topic                        schema                      content
===========================  ==========================  ======================================
/camera/color/image_raw      foxglove.RawImage           rgb8
/camera/depth/image_raw      foxglove.RawImage           16UC1 millimetres (or 32FC1 metres)
/camera/instance/image_raw   foxglove.RawImage           16UC1 instance ids, 0 = background
/camera/color/camera_info    foxglove.CameraCalibration  pinhole K, P; no distortion
/tf                          foxglove.FrameTransform     world -> camera (camera pose in world)
/scene                       mateqa.Scene (jsonschema)   JSON: parts, poses, scale, labels
===========================  ==========================  ======================================

Instance ids are 16UC1 so Foxglove displays them like any mono16 image; ids above 65535 are
refused. Every image has frame_id ``camera`` (OpenCV optical frame). Reading discovers topics by
schema name, so recordings from real cameras (other topic names, only depth, colour and
calibration) read too: depth is paired with the nearest colour frame within a tolerance.
"""

from __future__ import annotations

import json
import logging
import struct
from collections import deque
from collections.abc import Iterator
from contextlib import AbstractContextManager, ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, cast

import numpy as np
import numpy.typing as npt
import zstandard
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.message import DecodeError
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation

from cadio.errors import CaptureError
from cadio.records import CameraIntrinsics, FloatArray, RgbdFrame
from cadio.workspace import atomic_path

log = logging.getLogger(__name__)

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
INSTANCE_TOPIC = "/camera/instance/image_raw"
CAMERA_INFO_TOPIC = "/camera/color/camera_info"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/scene"

RAW_IMAGE = "foxglove.RawImage"
CALIBRATION = "foxglove.CameraCalibration"
TRANSFORM = "foxglove.FrameTransform"
SCENE_SCHEMA = "mateqa.Scene"

RGB8 = "rgb8"
DEPTH_MM = "16UC1"  # uint16 millimetres, 0 = missing (what ROS / RealSense drivers publish)
DEPTH_M = "32FC1"  # float32 metres, 0 = missing
INSTANCE_ENCODING = "16UC1"

WRITER_ID = "mateqa cadio.capture.mcap_io"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"

_COLOUR_ENCODINGS = {"rgb8": (3, [0, 1, 2]), "bgr8": (3, [2, 1, 0]), "rgba8": (4, [0, 1, 2]),
                     "bgra8": (4, [2, 1, 0]), "mono8": (1, [0, 0, 0]), "8UC3": (3, [0, 1, 2])}
_DEPTH_ENCODINGS = {"16UC1", "mono16", "32FC1"}
_EXPECTED = {COLOR_TOPIC: RAW_IMAGE, DEPTH_TOPIC: RAW_IMAGE, INSTANCE_TOPIC: RAW_IMAGE,
             CAMERA_INFO_TOPIC: CALIBRATION, TF_TOPIC: TRANSFORM}
_MAX_PENDING = 300  # depth images held while waiting for a calibration (10 s at 30 fps)
_ROLE_OF = {COLOR_TOPIC: "colour", DEPTH_TOPIC: "depth"}
# What a damaged file raises inside the mcap reader: short reads, bad CRCs, bad zstd frames.
_DAMAGE = (McapError, ValueError, struct.error, EOFError, zstandard.ZstdError)


def _stamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _ns(stamp: Timestamp) -> int:
    return int(stamp.seconds) * 1_000_000_000 + int(stamp.nanos)


def _raw(stamp: Timestamp, pixels: npt.NDArray[Any], encoding: str) -> RawImage:
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels)
    return RawImage(timestamp=stamp, frame_id=CAMERA_FRAME, width=w, height=h,
                    encoding=encoding, step=data.strides[0], data=data.tobytes())


def depth_to_mm(depth_m: npt.NDArray[np.float32]) -> npt.NDArray[np.uint16]:
    """(h, w) metres -> uint16 millimetres rounded to nearest, 0 where missing or out of range."""
    mm = np.nan_to_num(depth_m.astype(np.float64) * 1000.0, nan=0.0, posinf=0.0, neginf=0.0)
    return np.where((mm > 0) & (mm < 65535.5), np.round(mm), 0).astype("<u2")


def _calibration(stamp: Timestamp, k: CameraIntrinsics) -> CameraCalibration:
    return CameraCalibration(
        timestamp=stamp, frame_id=CAMERA_FRAME, width=k.width, height=k.height,
        distortion_model="plumb_bob", D=[0.0] * 5,
        K=[k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
        P=[k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0],
    )


def _transform(stamp: Timestamp, world_to_camera: FloatArray) -> FrameTransform:
    """FrameTransform world -> camera: Foxglove stores the child's pose in the parent frame."""
    c2w = np.linalg.inv(world_to_camera)
    x, y, z, w = Rotation.from_matrix(c2w[:3, :3]).as_quat()
    t = c2w[:3, 3]
    return FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME,
                          child_frame_id=CAMERA_FRAME,
                          translation=Vector3(x=t[0], y=t[1], z=t[2]),
                          rotation=Quaternion(x=x, y=y, z=z, w=w))


class CaptureWriter(AbstractContextManager["CaptureWriter"]):
    """Write RGB-D frames and a scene description to an MCAP file, atomically.

    Usage::

        with CaptureWriter(path) as w:
            w.write_scene(meta)
            for frame in frames:
                w.write_frame(frame)

    The file appears at ``path`` only when the block exits without an exception.
    """

    def __init__(self, path: Path | str, *, depth_encoding: str = DEPTH_MM,
                 chunk_size: int = 1 << 20, compression: str = "zstd") -> None:
        if depth_encoding not in (DEPTH_MM, DEPTH_M):
            raise ValueError(f"depth_encoding must be {DEPTH_MM} or {DEPTH_M}")
        self.path = Path(path)
        self.depth_encoding = depth_encoding
        self._chunk_size = chunk_size
        self._compression = CompressionType[compression.upper()]
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._stack = ExitStack()
        self._writer: Writer | None = None

    def __enter__(self) -> CaptureWriter:
        tmp = self._stack.enter_context(atomic_path(self.path))
        fh = self._stack.enter_context(tmp.open("wb"))
        # No attachment index group: the mcap writer would point a summary offset at an empty
        # group, which `pymcap-cli doctor` reports as an error.
        self._writer = Writer(fh, chunk_size=self._chunk_size, compression=self._compression,
                              index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA)
        self._writer.start(profile="", library=WRITER_ID)
        self._writer.add_metadata("mateqa.capture", {"writer": WRITER_ID,
                                                     "depth_encoding": self.depth_encoding})
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool | None:
        if exc_type is None and self._writer is not None:
            self._writer.finish()  # before the stack closes the file and renames it
        return self._stack.__exit__(exc_type, exc, tb)

    def _channel(self, topic: str, message: Any) -> int:
        if topic not in self._channels:
            assert self._writer is not None, "use CaptureWriter as a context manager"
            schema_id = self._writer.register_schema(
                name=message.DESCRIPTOR.full_name, encoding="protobuf",
                data=build_file_descriptor_set(type(message)).SerializeToString())
            self._channels[topic] = self._writer.register_channel(topic, "protobuf", schema_id)
        return self._channels[topic]

    def _put(self, topic: str, message: Any, ns: int) -> None:
        self._add(self._channel(topic, message), message.SerializeToString(), ns)

    def _add(self, channel: int, data: bytes, ns: int) -> None:
        assert self._writer is not None, "use CaptureWriter as a context manager"
        seq = self._sequence[channel] = self._sequence.get(channel, 0) + 1
        self._writer.add_message(channel, log_time=ns, data=data, publish_time=ns, sequence=seq)

    def write_frame(self, frame: RgbdFrame) -> None:
        """Write one frame: calibration, transform, colour, depth and (if known) instance ids."""
        k, ns = frame.intrinsics, frame.timestamp_ns
        shape = (k.height, k.width)
        if frame.colour.shape != (*shape, 3) or frame.depth.shape != shape:
            raise ValueError(f"frame images do not match the intrinsics' {k.width}x{k.height}")
        stamp = _stamp(ns)
        self._put(CAMERA_INFO_TOPIC, _calibration(stamp, k), ns)
        self._put(TF_TOPIC, _transform(stamp, frame.world_to_camera), ns)
        self._put(COLOR_TOPIC, _raw(stamp, frame.colour.astype(np.uint8), RGB8), ns)
        depth = (depth_to_mm(frame.depth) if self.depth_encoding == DEPTH_MM
                 else np.nan_to_num(frame.depth.astype("<f4"), nan=0.0, posinf=0.0))
        self._put(DEPTH_TOPIC, _raw(stamp, depth, self.depth_encoding), ns)
        if frame.instance is not None:
            ids = frame.instance
            if ids.min(initial=0) < 0 or ids.max(initial=0) > 0xFFFF:
                raise ValueError("instance ids must lie in [0, 65535] for 16UC1")
            self._put(INSTANCE_TOPIC, _raw(stamp, ids.astype("<u2"), INSTANCE_ENCODING), ns)

    def write_scene(self, meta: dict[str, Any], timestamp_ns: int = 0) -> None:
        """Write the scene description (JSON-ready dict) on ``/scene``; write it first."""
        assert self._writer is not None, "use CaptureWriter as a context manager"
        if SCENE_TOPIC not in self._channels:
            schema = json.dumps({"type": "object", "title": SCENE_SCHEMA}).encode()
            sid = self._writer.register_schema(SCENE_SCHEMA, "jsonschema", schema)
            self._channels[SCENE_TOPIC] = self._writer.register_channel(SCENE_TOPIC, "json", sid)
        self._add(self._channels[SCENE_TOPIC], json.dumps(meta).encode(), timestamp_ns)


def write_capture(path: Path | str, frames: Any, meta: dict[str, Any] | None = None,
                  depth_encoding: str = DEPTH_MM) -> int:
    """Write an iterable of frames (and the scene) to ``path``; returns the frame count."""
    n = 0
    with CaptureWriter(path, depth_encoding=depth_encoding) as w:
        if meta is not None:
            w.write_scene(meta)
        for frame in frames:
            w.write_frame(frame)
            n += 1
    return n


# ----------------------------------------------------------------------------------- reading


@dataclass
class _Msg:
    topic: str
    ts: int  # header stamp, ns (log time when the header has none)
    msg: Any


def _stream(path: Path, fh: IO[bytes]) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) records in file order; damage -> CaptureError."""
    count = 0
    try:
        reader = NonSeekingReader(fh, validate_crcs=True)
        for item in reader.iter_messages(log_time_order=False):
            count += 1
            yield item
    except _DAMAGE as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise CaptureError(path, f"truncated or corrupt after {count} complete messages "
                                 f"({detail})") from exc


def _summary(fh: IO[bytes]) -> Any:
    """The file's summary (schemas, channels, indexes), or None when missing or damaged."""
    try:
        return SeekingReader(fh).get_summary()
    except _DAMAGE:
        return None  # e.g. truncated: callers scan the stream instead
    finally:
        fh.seek(0)


def _aligned_depth_topic(summary: Any) -> str | None:
    """A depth topic registered to colour (ROS drivers name it "aligned_depth..."), if any:
    preferred over the raw depth topic that such recordings also carry."""
    if summary is None:
        return None
    return next((c.topic for c in summary.channels.values() if "aligned" in c.topic
                 and "depth" in c.topic and c.schema_id in summary.schemas
                 and summary.schemas[c.schema_id].name == RAW_IMAGE), None)


def _check_known(path: Path, channel: Any, schema: Any) -> None:
    expected = _EXPECTED.get(channel.topic)
    if channel.topic == SCENE_TOPIC and channel.message_encoding != "json":
        raise CaptureError(path, f"topic {SCENE_TOPIC} must be JSON, "
                                 f"got {channel.message_encoding!r}")
    if expected is None:
        return
    name = schema.name if schema is not None else "<none>"
    if name != expected or channel.message_encoding != "protobuf":
        raise CaptureError(path, f"topic {channel.topic} has schema {name} "
                                 f"({channel.message_encoding}), expected {expected} (protobuf)")


def _image_role(topic: str, msg: Any) -> str | None:
    if msg.encoding in _DEPTH_ENCODINGS:
        return "depth"
    if msg.encoding == "mono8" and not any(h in topic for h in ("color", "colour", "rgb")):
        return None  # infrared streams are mono8 too
    return "colour" if msg.encoding in _COLOUR_ENCODINGS else None


@dataclass
class _Topics:
    """Role of each channel, found from its topic or schema (and first image's encoding)."""

    depth_topic: str | None = None
    colour_topic: str | None = None
    roles: dict[int, str | None] = field(default_factory=dict)
    decoders: DecoderFactory = field(default_factory=DecoderFactory)

    def decode(self, path: Path, schema: Any, channel: Any, message: Any) -> Any:
        try:
            decoder = self.decoders.decoder_for(channel.message_encoding, schema)
            return decoder(message.data) if decoder is not None else None
        except (DecodeError, McapError, TypeError, ValueError) as exc:
            raise CaptureError(path, f"topic {channel.topic}: cannot decode: {exc}") from exc

    def role(self, path: Path, schema: Any, channel: Any, msg: Any) -> str | None:
        if channel.id not in self.roles:
            self.roles[channel.id] = self._assign(path, schema, channel, msg)
        return self.roles[channel.id]

    def _assign(self, path: Path, schema: Any, channel: Any, msg: Any) -> str | None:
        _check_known(path, channel, schema)
        name, topic = (schema.name if schema is not None else ""), channel.topic
        if msg is None:
            return None
        if name == CALIBRATION:
            return "info"
        if name == TRANSFORM:
            return "tf"
        if name != RAW_IMAGE:
            return None
        if topic == INSTANCE_TOPIC:
            return "instance"
        role = _image_role(topic, msg)
        if (role is None and topic in _EXPECTED) or _ROLE_OF.get(topic, role) != role:
            raise CaptureError(path, f"topic {topic} has unsupported encoding {msg.encoding!r}")
        wanted = {"depth": self.depth_topic, "colour": self.colour_topic}.get(role or "")
        if role is None or (wanted is not None and wanted != topic):
            log.info("ignoring image topic %s", topic)
            return None
        setattr(self, f"{role}_topic", topic)
        return role


def _colour_pixels(path: Path, m: _Msg) -> npt.NDArray[np.uint8]:
    channels, order = _COLOUR_ENCODINGS[m.msg.encoding]
    rows = _rows(path, m, channels)
    return np.ascontiguousarray(rows.reshape(m.msg.height, m.msg.width, channels)[..., order])


def _rows(path: Path, m: _Msg, row_items: int, dtype: str = "u1") -> npt.NDArray[Any]:
    """Pixel rows of a RawImage, honouring ``step`` (rows may be padded)."""
    img, itemsize = m.msg, np.dtype(dtype).itemsize
    row_bytes = img.width * row_items * itemsize
    if img.step < row_bytes or len(img.data) < img.step * img.height:
        raise CaptureError(path, f"topic {m.topic}: image data shorter than {img.width}x"
                                 f"{img.height} {img.encoding}")
    buf = np.frombuffer(img.data, dtype=np.uint8, count=img.step * img.height)
    rows = buf.reshape(img.height, img.step)[:, :row_bytes]
    return np.ascontiguousarray(rows).view(dtype).reshape(img.height, -1)


def _depth_metres(path: Path, m: _Msg, mm_scale: float) -> npt.NDArray[np.float32]:
    if m.msg.encoding == DEPTH_M:
        d = _rows(path, m, 1, "<f4")
        return np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)
    return (_rows(path, m, 1, "<u2").astype(np.float32) * np.float32(mm_scale))


def _intrinsics(calib: Any) -> CameraIntrinsics:
    k = list(calib.K) if any(calib.K) else [calib.P[i] for i in (0, 1, 2, 4, 5, 6, 8, 9, 10)]
    return CameraIntrinsics(int(calib.width), int(calib.height), float(k[0]), float(k[4]),
                            float(k[2]), float(k[5]))


def _world_to_camera(tf: Any) -> FloatArray:
    q, t = tf.rotation, tf.translation
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    c2w[:3, 3] = [t.x, t.y, t.z]
    return np.asarray(np.linalg.inv(c2w), dtype=np.float64)


@dataclass
class _Pairer:
    """Streams depth images and pairs each with the nearest colour, instance image and camera
    transform within ``tol`` ns; a depth image is settled once the stream has moved ``tol``
    past it (so a nearer partner can no longer arrive) or at the end of the stream."""

    tol: int
    depth: deque[_Msg] = field(default_factory=deque)
    others: dict[str, deque[_Msg]] = field(
        default_factory=lambda: {r: deque() for r in ("colour", "instance", "tf")})
    calib: dict[str, Any] = field(default_factory=dict)  # frame_id -> latest calibration

    def add(self, role: str, m: _Msg) -> None:
        if role == "info":
            self.calib[m.msg.frame_id] = m.msg
        elif role == "depth":
            self.depth.append(m)
        else:
            self.others[role].append(m)
            # Without a pending depth image nothing older than a tolerance behind can pair.
            self._prune(self.depth[0].ts - self.tol if self.depth else m.ts - 2 * self.tol)

    def _prune(self, horizon: int) -> None:
        for q in self.others.values():
            while q and q[0].ts < horizon:
                q.popleft()

    def settled(self, now: int | None) -> Iterator[tuple[_Msg, dict[str, _Msg | None], Any]]:
        """Pairs ready at stream time ``now`` (None: end of stream, settle everything)."""
        while self.depth and (now is None or now > self.depth[0].ts + self.tol):
            d = self.depth[0]
            calib = self._calibration(d)
            if calib is None:
                return  # it may still come; at the end of the stream the reader says so
            self.depth.popleft()
            match = {r: self._nearest(r, d) for r in self.others}
            self._prune(d.ts - self.tol)
            if match["colour"] is None:
                log.debug("depth at %d ns has no colour within %d ns; skipped", d.ts, self.tol)
                continue
            yield d, match, calib

    def _nearest(self, role: str, d: _Msg) -> _Msg | None:
        cands = [m for m in self.others[role] if abs(m.ts - d.ts) <= self.tol
                 and (role != "tf" or m.msg.child_frame_id == d.msg.frame_id)]
        return min(cands, key=lambda m: abs(m.ts - d.ts), default=None)

    def _calibration(self, d: _Msg) -> Any:
        if d.msg.frame_id in self.calib:
            return self.calib[d.msg.frame_id]
        sized = [c for c in self.calib.values()
                 if (c.width, c.height) == (d.msg.width, d.msg.height)]
        return sized[0] if sized else None


def _frame(path: Path, d: _Msg, match: dict[str, _Msg | None], calib: Any,
           pose: FloatArray, mm_scale: float) -> RgbdFrame:
    colour = match["colour"]
    assert colour is not None
    k = _intrinsics(calib)
    depth = _depth_metres(path, d, mm_scale)
    rgb = _colour_pixels(path, colour)
    if depth.shape != (k.height, k.width) or rgb.shape[:2] != depth.shape:
        raise CaptureError(path, f"{d.topic} {depth.shape[::-1]}, {colour.topic} "
                                 f"{rgb.shape[1::-1]} and calibration {k.width}x{k.height} "
                                 "differ: depth must be registered to colour")
    inst = match["instance"]
    tf = match["tf"]
    meta = {"depth_topic": d.topic, "colour_topic": colour.topic,
            "colour_offset_ns": colour.ts - d.ts, "pose_source": "tf" if tf else "given"}
    return RgbdFrame(
        timestamp_ns=d.ts, intrinsics=k, colour=rgb, depth=depth,
        world_to_camera=_world_to_camera(tf.msg) if tf else np.array(pose, dtype=np.float64),
        instance=None if inst is None else _rows(path, inst, 1, "<u2").astype(np.int32),
        meta=meta,
    )


def read_capture(path: Path | str, *, pose: FloatArray | None = None,
                 tolerance_ns: int = 20_000_000, depth_scale_m: float = 0.001,
                 depth_topic: str | None = None,
                 colour_topic: str | None = None) -> Iterator[RgbdFrame]:
    """Yield the RGB-D frames of an MCAP capture, written here or recorded by a real camera.

    Topics are found by schema (foxglove.RawImage by encoding, CameraCalibration,
    FrameTransform whose child is the depth image's frame); our own topic names are checked.
    Each depth image is paired with the nearest colour image (and instance image and transform,
    when present) within ``tolerance_ns``; depth without colour is skipped.

    Args:
        path: the .mcap file.
        pose: world_to_camera (4, 4), metres, for frames without a transform (default identity).
        tolerance_ns: pairing tolerance, ns (20 ms: half a 30 fps frame plus slack).
        depth_scale_m: metres per unit of 16UC1 depth (1 mm, the ROS convention).
        depth_topic, colour_topic: pick topics when a recording has several.
    Yields:
        RgbdFrame with depth (h, w) float32 metres (0 = missing), instance ids when present.
    Raises:
        CaptureError: after the last complete frame of a truncated or corrupt file; for a wrong
            schema or encoding on a known topic; when no calibration fits the depth images.
    """
    path = Path(path)
    default_pose = np.eye(4) if pose is None else np.asarray(pose, dtype=np.float64)
    pairer = _Pairer(tolerance_ns)

    def emit(now: int | None) -> Iterator[RgbdFrame]:
        for d, match, calib in pairer.settled(now):
            yield _frame(path, d, match, calib, default_pose, depth_scale_m)

    with path.open("rb") as fh:
        topics = _Topics(depth_topic or _aligned_depth_topic(_summary(fh)), colour_topic)
        try:
            for schema, channel, message in _stream(path, fh):
                m = _decode_known(path, topics, schema, channel, message)
                if m is not None:
                    pairer.add(*m)
                    yield from emit(m[1].ts)
                if len(pairer.depth) > _MAX_PENDING:
                    raise CaptureError(path, f"no {CALIBRATION} matches depth topic "
                                             f"{topics.depth_topic} in {_MAX_PENDING} images")
        except CaptureError:
            yield from emit(None)  # every complete frame before the damage
            raise
    yield from emit(None)
    if pairer.depth:
        raise CaptureError(path, f"no {CALIBRATION} matches depth topic {topics.depth_topic}")
    for role, topic in (("depth", topics.depth_topic), ("colour", topics.colour_topic)):
        if topic is None:
            raise CaptureError(path, f"no {role} image topic ({RAW_IMAGE}) found")


def _decode_known(path: Path, topics: _Topics, schema: Any, channel: Any,
                  message: Any) -> tuple[str, _Msg] | None:
    """Decode a message whose channel has (or may have) a role; None for everything else."""
    role = topics.roles.get(channel.id, "")
    if role is None or channel.topic == SCENE_TOPIC:
        if channel.topic == SCENE_TOPIC:
            _check_known(path, channel, schema)
        return None
    msg = topics.decode(path, schema, channel, message)
    role = topics.role(path, schema, channel, msg)
    if role is None:
        return None
    stamp = _ns(msg.timestamp) if msg.HasField("timestamp") else message.log_time
    return role, _Msg(channel.topic, stamp, msg)


def read_scene_meta(path: Path | str) -> dict[str, Any] | None:
    """The JSON scene description on ``/scene``, or None when the capture has none.

    Raises:
        CaptureError: the file is damaged before the scene message, or ``/scene`` is not JSON.
    """
    path = Path(path)
    with path.open("rb") as fh:
        summary = _summary(fh)
        if summary is not None and all(c.topic != SCENE_TOPIC for c in summary.channels.values()):
            return None
        for schema, channel, message in _stream(path, fh):
            if channel.topic == SCENE_TOPIC:
                _check_known(path, channel, schema)
                return cast(dict[str, Any], json.loads(message.data))
    return None

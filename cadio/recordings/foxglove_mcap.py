"""Captures as MCAP files with Foxglove protobuf schemas: the writer, and the Foxglove dialect.

Files are zstd-chunked, indexed and carry a summary (the plain ``mcap`` writer with
``foxglove-schemas-protobuf`` message classes), so Foxglove and any MCAP reader open them.
Topics (constants below):

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
refused. Every image has frame_id ``camera`` (OpenCV optical frame). Reading (``FOXGLOVE``, used
by ``cadio.recordings.mcap_io``) turns RawImage, CameraCalibration and FrameTransform(s) messages
of any topic into the records of ``cadio.recordings.recording``.
"""

from __future__ import annotations

import json
from contextlib import AbstractContextManager, ExitStack
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation

from cadio.recordings.recording import CalibrationMsg, Dialect, ImageMsg, Record, TransformMsg
from cadio.records import CameraIntrinsics, FloatArray, RgbdFrame
from cadio.workspace import atomic_path

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
INSTANCE_TOPIC = "/camera/instance/image_raw"
CAMERA_INFO_TOPIC = "/camera/color/camera_info"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/scene"

RAW_IMAGE = "foxglove.RawImage"
CALIBRATION = "foxglove.CameraCalibration"
TRANSFORM = "foxglove.FrameTransform"
TRANSFORMS = "foxglove.FrameTransforms"
SCENE_SCHEMA = "mateqa.Scene"

RGB8 = "rgb8"
DEPTH_MM = "16UC1"  # uint16 millimetres, 0 = missing (what ROS / RealSense drivers publish)
DEPTH_M = "32FC1"  # float32 metres, 0 = missing
INSTANCE_ENCODING = "16UC1"

WRITER_ID = "mateqa cadio.recordings.mcap_io"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"


def _stamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


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


def _ns(stamp: Timestamp, log_time: int) -> int:
    ns = int(stamp.seconds) * 1_000_000_000 + int(stamp.nanos)
    return ns or log_time


def _image_record(topic: str, msg: Any, log_time: int) -> ImageMsg:
    return ImageMsg(topic, _ns(msg.timestamp, log_time), msg.frame_id, int(msg.width),
                    int(msg.height), msg.encoding, msg.data, step=int(msg.step))


def _calibration_record(topic: str, msg: Any, log_time: int) -> CalibrationMsg:
    return CalibrationMsg(topic, _ns(msg.timestamp, log_time), msg.frame_id, int(msg.width),
                          int(msg.height), tuple(msg.K), tuple(msg.P))


def _edge(msg: Any, log_time: int) -> TransformMsg:
    t, q = msg.translation, msg.rotation
    return TransformMsg(_ns(msg.timestamp, log_time), msg.parent_frame_id, msg.child_frame_id,
                        (t.x, t.y, t.z), (q.x, q.y, q.z, q.w))


def _records(kind: str, topic: str, msg: Any, log_time: int) -> list[Record]:
    if kind == "image":
        return [_image_record(topic, msg, log_time)]
    if kind == "calibration":
        return [_calibration_record(topic, msg, log_time)]
    edges = msg.transforms if hasattr(msg, "transforms") else [msg]
    return [_edge(e, log_time) for e in edges]


FOXGLOVE = Dialect(
    name="Foxglove", message_encoding="protobuf",
    kinds={RAW_IMAGE: "image", CALIBRATION: "calibration", TRANSFORM: "tf", TRANSFORMS: "tf"},
    records=_records, decoders=DecoderFactory)

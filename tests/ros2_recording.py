"""ROS 2 recordings for the tests, written as ``ros2 bag record`` writes them: profile ``ros2``,
``cdr`` messages, ``ros2msg`` schemas (the concatenated message definitions), CDR bytes from
Foxglove's ``mcap_ros2`` writer.

``DEFINITIONS`` holds the fields of each message type as ROS 2 ships them (common_interfaces,
geometry2, rcl_interfaces), without the comments; ``msgdef`` concatenates a type's definition
and those of the types it uses, as rosbag2 stores them in the schema record.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap_ros2.writer import Writer
from scipy.spatial.transform import Rotation

from cadio.records import RgbdFrame

DEFINITIONS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/String": "string data\n",
    "std_msgs/Float32": "float32 data\n",
    "sensor_msgs/Image": "std_msgs/Header header\nuint32 height\nuint32 width\n"
                         "string encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/RegionOfInterest": "uint32 x_offset\nuint32 y_offset\nuint32 height\n"
                                    "uint32 width\nbool do_rectify\n",
    "sensor_msgs/CameraInfo": "std_msgs/Header header\nuint32 height\nuint32 width\n"
                              "string distortion_model\nfloat64[] d\nfloat64[9] k\n"
                              "float64[9] r\nfloat64[12] p\nuint32 binning_x\n"
                              "uint32 binning_y\nRegionOfInterest roi\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\n"
                                      "Transform transform\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/Imu": "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
                       "float64[9] orientation_covariance\n"
                       "geometry_msgs/Vector3 angular_velocity\n"
                       "float64[9] angular_velocity_covariance\n"
                       "geometry_msgs/Vector3 linear_acceleration\n"
                       "float64[9] linear_acceleration_covariance\n",
    "rcl_interfaces/Log": "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\n"
                          "byte FATAL=50\nbuiltin_interfaces/Time stamp\nuint8 level\n"
                          "string name\nstring msg\nstring file\nstring function\n"
                          "uint32 line\n",
}
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string", "wstring"}
SEPARATOR = "=" * 80


def _uses(name: str) -> list[str]:
    pkg = name.split("/")[0]
    out = []
    for line in DEFINITIONS[name].splitlines():
        ftype = re.split(r"[\[\s]", line.strip())[0]
        if not ftype or "=" in line or ftype in _PRIMITIVES:
            continue
        out.append(ftype if "/" in ftype else f"{pkg}/{ftype}")
    return out


def msgdef(datatype: str) -> str:
    """The concatenated definition of ``pkg/msg/Type`` and every type it uses."""
    root = datatype.replace("/msg/", "/")
    order, todo = [], [root]
    while todo:
        name = todo.pop(0)
        if name not in order:
            order.append(name)
            todo.extend(_uses(name))
    parts = [DEFINITIONS[root]] + [f"{SEPARATOR}\nMSG: {n}\n{DEFINITIONS[n]}" for n in order[1:]]
    return "".join(parts)


def header(ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": frame_id}


def image(ns: int, frame_id: str, pixels: np.ndarray, encoding: str, pad: int = 0
          ) -> dict[str, Any]:
    """A sensor_msgs/Image of ``pixels`` (little-endian), each row padded with ``pad`` bytes."""
    rows = np.ascontiguousarray(pixels).reshape(pixels.shape[0], -1).view(np.uint8)
    padded = np.zeros((rows.shape[0], rows.shape[1] + pad), dtype=np.uint8)
    padded[:, : rows.shape[1]] = rows
    return {"header": header(ns, frame_id), "height": pixels.shape[0], "width": pixels.shape[1],
            "encoding": encoding, "is_bigendian": 0, "step": padded.shape[1],
            "data": padded.tobytes()}


def camera_info(ns: int, frame_id: str, frame: RgbdFrame) -> dict[str, Any]:
    k = frame.intrinsics
    return {"header": header(ns, frame_id), "height": k.height, "width": k.width,
            "distortion_model": "plumb_bob", "d": [0.0] * 5,
            "k": [k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], "r": [1, 0, 0, 0, 1, 0, 0, 0, 1],
            "p": [k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0]}


def transform(ns: int, parent: str, child: str, child_to_parent: np.ndarray) -> dict[str, Any]:
    """A geometry_msgs/TransformStamped: ``child``'s pose in ``parent`` (4, 4)."""
    x, y, z, w = Rotation.from_matrix(child_to_parent[:3, :3]).as_quat()
    tx, ty, tz = child_to_parent[:3, 3]
    return {"header": header(ns, parent), "child_frame_id": child,
            "transform": {"translation": {"x": tx, "y": ty, "z": tz},
                          "rotation": {"x": x, "y": y, "z": z, "w": w}}}


# The optical frame in its camera link (REP 103: link x forward, y left, z up; optical frame
# x right, y down, z forward).
OPTICAL_IN_LINK = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])


def link_on_base() -> np.ndarray:
    """A camera link on a robot's base link: 0.5 m up, 0.1 m forward, yawed 10 degrees."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    m[:3, 3] = (0.1, 0.0, 0.5)
    return m


@dataclass
class Recording:
    """A ROS 2 MCAP being written: ``put(topic, datatype, message, stamp_ns)``; log times are
    ``log_time(stamp_ns)``."""

    writer: Writer
    log_time: Callable[[int], int] = lambda ns: ns
    schemas: dict[str, Any] = field(default_factory=dict)

    def put(self, topic: str, datatype: str, message: dict[str, Any], ns: int) -> None:
        if datatype not in self.schemas:
            self.schemas[datatype] = self.writer.register_msgdef(datatype, msgdef(datatype))
        t = self.log_time(ns)
        self.writer.write_message(topic, self.schemas[datatype], message, log_time=t,
                                  publish_time=t)


@contextmanager
def ros2_recording(path: Path, log_time: Callable[[int], int] = lambda ns: ns,
                   chunk_size: int = 1 << 20) -> Iterator[Recording]:
    """Write a ROS 2 MCAP at ``path`` (zstd chunks, indexed, with a summary)."""
    with path.open("wb") as fh:
        writer = Writer(fh, chunk_size=chunk_size)
        yield Recording(writer, log_time)
        writer.finish()


def write_ros2_capture(path: Path, frames: Sequence[RgbdFrame], *, scene: dict | None = None,
                       depth_encoding: str = "16UC1", chunk_size: int = 1 << 20,
                       extra: Iterable[Callable[[Recording, int, RgbdFrame], None]] = ()
                       ) -> None:
    """Frames as a robot with a RealSense-style camera records them: a moving base on /tf
    (world -> base_link at every frame), the camera on it on /tf_static (base_link ->
    camera_link -> camera_color_optical_frame), depth registered to colour on
    /camera/aligned_depth_to_color/image_raw (16UC1 mm or 32FC1 m) beside an unregistered raw
    depth topic, bgr8 colour with padded rows, both camera infos, instance ids, and the scene
    as a std_msgs/String of JSON on /scene. ``extra`` writers add topics per frame."""
    optical = "camera_color_optical_frame"
    optical_on_base = link_on_base() @ OPTICAL_IN_LINK
    with ros2_recording(path, chunk_size=chunk_size) as rec:
        t0 = frames[0].timestamp_ns
        if scene is not None:
            rec.put("/scene", "std_msgs/msg/String", {"data": json.dumps(scene)}, t0)
        rec.put("/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": [
            transform(t0, "base_link", "camera_link", link_on_base()),
            transform(t0, "camera_link", optical, OPTICAL_IN_LINK)]}, t0)
        for f in frames:
            ns = f.timestamp_ns
            base = np.linalg.inv(f.world_to_camera) @ np.linalg.inv(optical_on_base)
            rec.put("/tf", "tf2_msgs/msg/TFMessage",
                    {"transforms": [transform(ns, "world", "base_link", base)]}, ns)
            for topic in ("/camera/color/camera_info",
                          "/camera/aligned_depth_to_color/camera_info"):
                rec.put(topic, "sensor_msgs/msg/CameraInfo", camera_info(ns, optical, f), ns)
            rec.put("/camera/color/image_raw", "sensor_msgs/msg/Image",
                    image(ns, optical, f.colour[..., ::-1], "bgr8", pad=8), ns)
            depth = (np.round(f.depth.astype(np.float64) * 1000).astype("<u2")
                     if depth_encoding in ("16UC1", "mono16") else f.depth.astype("<f4"))
            raw = np.zeros((f.depth.shape[0] // 2, f.depth.shape[1] // 2), dtype="<u2")
            rec.put("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image",
                    image(ns, "camera_depth_optical_frame", raw, "16UC1"), ns)
            rec.put("/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image",
                    image(ns, optical, depth, depth_encoding), ns)
            if f.instance is not None:
                rec.put("/camera/instance/image_raw", "sensor_msgs/msg/Image",
                        image(ns, optical, f.instance.astype("<u2"), "16UC1"), ns)
            for add in extra:
                add(rec, ns, f)

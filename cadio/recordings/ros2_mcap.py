"""The ROS 2 dialect of MCAP: what ``ros2 bag record`` writes (the default storage since Iron).

Channels have message encoding ``cdr`` and ``ros2msg`` schemas (the concatenated message
definitions). The reader (``cadio.recordings.mcap_io``) uses four of them and skips every other
topic a robot logs:

===============================  ==============================================================
schema                           read as
===============================  ==============================================================
sensor_msgs/msg/Image            depth 16UC1 / mono16 (1 mm units) or 32FC1 (m); colour rgb8,
                                 bgr8, rgba8, bgra8, mono8; instance ids on an "instance" topic
sensor_msgs/msg/CompressedImage  PNG / JPEG colour; compressedDepth (16UC1 or 32FC1) depth
sensor_msgs/msg/CameraInfo       k (or p) and the image size; distortion is not applied
tf2_msgs/msg/TFMessage           /tf (timed) and /tf_static (static) edges of the frame tree
===============================  ==============================================================

CDR is decoded with Foxglove's ``mcap-ros2-support`` (``mcap_ros2``), not with the third-party
``mcap-ros2-support-fast`` that ``pymcap-cli`` (a development tool here) pulls in: it comes from
the project that makes the ``mcap`` reader this package reads with, plugs into that reader's
decoder-factory protocol, and is MIT-licensed, where the fast one is GPL-3.0 (a copyleft
dependency of a product shipped as a package and an image) and built for another reader
(``small-mcap``). Speed does not argue for the fast one on RGB-D: an image's pixels are one byte
slice in either, and on 30 to 120 views of 640x480 it took longer than ``mcap_ros2`` to decode
every message (it generates code per schema first; ``bench/speed/recordings.py``).
"""

from __future__ import annotations

from typing import Any

from mcap_ros2.decoder import DecoderFactory

from cadio.recordings.recording import (
    CalibrationMsg,
    Dialect,
    ImageMsg,
    Record,
    TransformMsg,
    compressed_encoding,
    compressed_size,
)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"  # a JSON scene description on /scene, as a simulator logs it
TF_STATIC_TOPIC = "/tf_static"

_KINDS = {IMAGE: "image", COMPRESSED_IMAGE: "compressed", CAMERA_INFO: "calibration",
          TF_MESSAGE: "tf"}


def _ns(header: Any, log_time: int) -> int:
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns or log_time


def _image(topic: str, msg: Any, log_time: int) -> ImageMsg:
    return ImageMsg(topic, _ns(msg.header, log_time), msg.header.frame_id, int(msg.width),
                    int(msg.height), msg.encoding, bytes(msg.data), step=int(msg.step),
                    big_endian=bool(msg.is_bigendian))


def _compressed(topic: str, msg: Any, log_time: int) -> ImageMsg:
    encoding, payload = compressed_encoding(msg.format)
    data = bytes(msg.data)
    width, height = compressed_size(payload, data)
    return ImageMsg(topic, _ns(msg.header, log_time), msg.header.frame_id, width, height,
                    encoding, data, compressed=payload)


def _calibration(topic: str, msg: Any, log_time: int) -> CalibrationMsg:
    return CalibrationMsg(topic, _ns(msg.header, log_time), msg.header.frame_id, int(msg.width),
                          int(msg.height), tuple(msg.k), tuple(msg.p))


def _edges(topic: str, msg: Any, log_time: int) -> list[TransformMsg]:
    static = topic.rstrip("/").endswith(TF_STATIC_TOPIC)
    out = []
    for ts in msg.transforms:
        t, q = ts.transform.translation, ts.transform.rotation
        out.append(TransformMsg(_ns(ts.header, log_time), ts.header.frame_id, ts.child_frame_id,
                                (t.x, t.y, t.z), (q.x, q.y, q.z, q.w), static=static))
    return out


def _records(kind: str, topic: str, msg: Any, log_time: int) -> list[Record]:
    if kind == "image":
        return [_image(topic, msg, log_time)]
    if kind == "compressed":
        return [_compressed(topic, msg, log_time)]
    if kind == "calibration":
        return [_calibration(topic, msg, log_time)]
    return list(_edges(topic, msg, log_time))


ROS2 = Dialect(name="ROS 2", message_encoding="cdr",
               kinds={**_KINDS, **{k.replace("/msg/", "/"): v for k, v in _KINDS.items()}},
               records=_records, decoders=DecoderFactory)

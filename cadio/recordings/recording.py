"""What an RGB-D recording holds, in one form for both MCAP dialects, and its pixels as arrays.

The Foxglove (protobuf) and ROS 2 (CDR) readers turn their messages into these records, so that
pairing, poses and frames (``cadio.recordings.pairing``) are written once: ``ImageMsg`` (raw rows or
a compressed payload), ``CalibrationMsg`` (pinhole K and P) and ``TransformMsg`` (a parent ->
child edge of the transform tree). No MCAP library is imported here.

Image encodings are the ROS ones (``sensor_msgs/image_encodings.hpp``), which Foxglove's RawImage
shares: depth ``16UC1`` or ``mono16`` (uint16, ``depth_scale_m`` metres a unit, 1 mm by the ROS
convention) or ``32FC1`` (float32 metres); colour ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``,
``mono8``; instance ids ``16UC1``/``mono16``/``32SC1``. Compressed images are PNG or JPEG
(``sensor_msgs/CompressedImage``), and depth from ROS's ``compressedDepth`` transport (a 12-byte
header, then a 16-bit PNG of millimetres or of quantised inverse depth for 32FC1).
"""

from __future__ import annotations

import io
import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.records import CameraIntrinsics

# encoding -> (channels, order of the source channels giving R, G, B)
COLOUR_ENCODINGS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)),
                    "bgra8": (4, (2, 1, 0)), "mono8": (1, (0, 0, 0)), "8UC3": (3, (0, 1, 2))}
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
INSTANCE_ENCODINGS = {"16UC1": "u2", "mono16": "u2", "32SC1": "i4"}
_DEPTH_HEADER = struct.Struct("<i2f")  # compressedDepth: format enum, depthQuantA, depthQuantB


@dataclass(frozen=True, eq=False)
class ImageMsg:
    """One image message. ``stamp_ns``: the header stamp (the log time where it is zero).

    Raw: ``data`` holds ``height`` rows of ``step`` bytes. Compressed: ``compressed`` names the
    payload ("png", "jpeg", or "compressedDepth"), ``encoding`` is the pixels' once decoded.
    """

    topic: str
    stamp_ns: int
    frame_id: str
    width: int
    height: int
    encoding: str
    data: bytes
    step: int = 0
    big_endian: bool = False
    compressed: str = ""


@dataclass(frozen=True)
class CalibrationMsg:
    """A pinhole calibration: ``k`` the 3x3 and ``p`` the 3x4 matrix, row-major (either may be
    zeros: an uncalibrated camera), for images of ``width`` x ``height`` pixels."""

    topic: str
    stamp_ns: int
    frame_id: str
    width: int
    height: int
    k: tuple[float, ...]
    p: tuple[float, ...]

    def intrinsics(self) -> CameraIntrinsics:
        k = self.k if any(self.k) else tuple(self.p[i] for i in (0, 1, 2, 4, 5, 6, 8, 9, 10))
        return CameraIntrinsics(self.width, self.height, float(k[0]), float(k[4]), float(k[2]),
                                float(k[5]))


@dataclass(frozen=True)
class TransformMsg:
    """The pose of frame ``child`` in frame ``parent`` (it maps child coordinates to the
    parent's): translation (x, y, z) metres, rotation quaternion (x, y, z, w). Static transforms
    (ROS's /tf_static) hold at every time."""

    stamp_ns: int
    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    static: bool = False


Record = ImageMsg | CalibrationMsg | TransformMsg


@dataclass(frozen=True)
class Dialect:
    """How one MCAP dialect's messages become records.

    kinds: schema name -> "image", "calibration" or "tf" (other schemas are not read).
    records: (kind, topic, decoded message, log time ns) -> the records it holds.
    decoders: makes a fresh decoder factory (``mcap``'s protocol: factories cache decoders by
        schema id, which differ from file to file).
    """

    name: str
    message_encoding: str
    kinds: Mapping[str, str]
    records: Callable[[str, str, Any, int], list[Record]]
    decoders: Callable[[], Any]


class PixelError(ValueError):
    """An image's bytes do not hold what its header says (the reader adds file and topic)."""


# Image sides a recording may hold: below 32 pixels no part can be told from the table; above
# 16384 no camera's (its decoded pixels alone would take gigabytes).
MIN_SIDE, MAX_SIDE = 32, 16384
SIDES = f"{MIN_SIDE} to {MAX_SIDE} pixels a side"


def size_problem(img: ImageMsg) -> str | None:
    """What is wrong with an image's size (``MIN_SIDE``, ``MAX_SIDE``), or None."""
    if MIN_SIDE <= img.width <= MAX_SIDE and MIN_SIDE <= img.height <= MAX_SIDE:
        return None
    return f"{img.width}x{img.height} pixels"


def intrinsics_problem(k: CameraIntrinsics) -> str | None:
    """What is wrong with a camera's intrinsics (a focal length that is not a finite number
    above 0, a principal point that is not finite), or None: back-projection divides by the
    focal lengths."""
    if all(math.isfinite(v) for v in (k.fx, k.fy, k.cx, k.cy)) and k.fx > 0 and k.fy > 0:
        return None
    return f"fx={k.fx:g}, fy={k.fy:g}, cx={k.cx:g}, cy={k.cy:g}"


def compressed_encoding(fmt: str) -> tuple[str, str]:
    """(pixel encoding, payload) of a CompressedImage ``format`` string: "16UC1;
    compressedDepth png" -> ("16UC1", "compressedDepth"), "rgb8; jpeg compressed bgr8" ->
    ("rgb8", "jpeg"), "16UC1; png compressed 16UC1" -> ("16UC1", "png"), a bare "png" or
    "jpeg" -> ("rgb8", that): JPEG and PNG colour decode to RGB whatever the source order."""
    head, _, rest = (s.strip() for s in fmt.partition(";"))
    if "compresseddepth" in fmt.lower():
        return head or "16UC1", "compressedDepth"
    payload = (rest or head).split()[0].lower() if (rest or head) else ""
    payload = "jpeg" if payload in ("jpg", "jpeg") else payload
    known = (*COLOUR_ENCODINGS, *DEPTH_ENCODINGS, *INSTANCE_ENCODINGS)
    return (head if rest and head in known else "rgb8"), payload


def compressed_size(fmt: str, data: bytes) -> tuple[int, int]:
    """(width, height) of a compressed payload, from its header alone.

    Raises:
        PixelError: the payload is not an image the reader knows.
    """
    from PIL import Image, UnidentifiedImageError

    body = data[_DEPTH_HEADER.size:] if fmt == "compressedDepth" else data
    try:
        with Image.open(io.BytesIO(body)) as img:
            return int(img.width), int(img.height)
    except Image.DecompressionBombError as exc:  # declares billions of pixels: never decoded
        raise PixelError(f"{fmt} image declares more pixels than any camera gives ({exc})"
                         ) from exc
    except (UnidentifiedImageError, OSError) as exc:
        raise PixelError(f"{fmt} payload is not an image ({exc})") from exc


def _decompressed(img: ImageMsg) -> npt.NDArray[np.generic]:
    """Pixels of a compressed image: (h, w) or (h, w, c) as PIL decodes them."""
    from PIL import Image, UnidentifiedImageError

    body = img.data[_DEPTH_HEADER.size:] if img.compressed == "compressedDepth" else img.data
    try:
        with Image.open(io.BytesIO(body)) as pil:
            pixels = np.asarray(pil)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
        raise PixelError(f"cannot decode {img.compressed} image ({exc})") from exc
    if pixels.shape[:2] != (img.height, img.width):
        raise PixelError(f"{img.compressed} image is {pixels.shape[1]}x{pixels.shape[0]}, its "
                         f"header said {img.width}x{img.height}")
    return pixels


def _rows(img: ImageMsg, channels: int, dtype: str) -> npt.NDArray[np.generic]:
    """(h, w * channels) pixels of a raw image, honouring ``step`` (rows may be padded) and
    the byte order; bytes come back as a read-only view of the message's data."""
    item = np.dtype(dtype).itemsize
    row_bytes = img.width * channels * item
    step = img.step or row_bytes
    if step < row_bytes or len(img.data) < step * img.height:
        raise PixelError(f"image data shorter than {img.width}x{img.height} {img.encoding}")
    buf = np.frombuffer(img.data, dtype=np.uint8, count=step * img.height)
    rows = buf.reshape(img.height, step)[:, :row_bytes]
    if item == 1:
        return rows  # a view: the caller's own copy drops the padding
    typed = np.dtype(dtype).newbyteorder(">" if img.big_endian else "<")
    return np.ascontiguousarray(rows).view(typed)


def colour_pixels(img: ImageMsg) -> npt.NDArray[np.uint8]:
    """(h, w, 3) uint8 RGB of a colour image."""
    if img.compressed:
        pixels = _decompressed(img)
        if pixels.dtype != np.uint8:
            raise PixelError(f"compressed colour image has {pixels.dtype} pixels, not 8-bit")
        rgb = np.repeat(pixels[..., None], 3, axis=2) if pixels.ndim == 2 else pixels[..., :3]
        return np.array(rgb, dtype=np.uint8)  # a writable copy
    channels, order = COLOUR_ENCODINGS[img.encoding]
    rows = _rows(img, channels, "u1").reshape(img.height, img.width, channels)
    return np.asarray(rows[..., list(order)], dtype=np.uint8)  # a copy, 10x a slice's speed


def depth_metres(img: ImageMsg, depth_scale_m: float) -> npt.NDArray[np.float32]:
    """(h, w) float32 metres of a depth image, 0 where missing; uint16 depth is
    ``depth_scale_m`` metres a unit."""
    if img.compressed == "compressedDepth" and img.encoding == "32FC1":
        return _inverse_depth(img)
    if img.compressed:
        raw = _decompressed(img)
        if raw.ndim != 2 or raw.dtype.kind not in "ui":
            raise PixelError("compressed depth is not a single-channel integer image")
        return (raw.astype(np.float32) * np.float32(depth_scale_m)).astype(np.float32)
    if img.encoding == "32FC1":
        d = _rows(img, 1, "f4").astype(np.float32)
        return np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)
    return _rows(img, 1, "u2").astype(np.float32) * np.float32(depth_scale_m)


def _inverse_depth(img: ImageMsg) -> npt.NDArray[np.float32]:
    """32FC1 through compressedDepth: a 16-bit PNG of q = A / depth + B (0 = missing)."""
    if len(img.data) < _DEPTH_HEADER.size:
        raise PixelError("compressedDepth payload shorter than its header")
    _, quant_a, quant_b = _DEPTH_HEADER.unpack_from(img.data)
    q = _decompressed(img).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(q != 0, quant_a / (q - quant_b), 0.0)
    return d.astype(np.float32)


def instance_ids(img: ImageMsg) -> npt.NDArray[np.int32]:
    """(h, w) int32 instance ids (0 = background)."""
    if img.compressed:
        return _decompressed(img).astype(np.int32)
    return _rows(img, 1, INSTANCE_ENCODINGS[img.encoding]).astype(np.int32)

"""Which channel of a recording is what: depth, colour, instance ids, camera info or transforms.

Channels are told apart by schema (either dialect's, ``DIALECTS``) and, for images, by the first
image's encoding and the topic's name: 16UC1 and 32FC1 are depth, and so is mono16 on a topic
named for depth (RealSense labels its depth so; 16-bit infrared is mono16 too); rgb8, bgr8,
rgba8, bgra8 and compressed PNG/JPEG are colour, and so is mono8 on a topic named for colour
(infrared is mono8 too); a topic named for instances holds instance ids. Where a recording has
several depth or colour topics, the first one seen is used, except that a topic registered to
colour ("aligned_depth...") is preferred, and the compressed twin of a raw topic is skipped.
Our own topic names must hold what they promise (``CaptureTopicError`` otherwise); every other
topic is skipped.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from google.protobuf.message import DecodeError
from mcap.exceptions import McapError

from cadio.errors import CaptureTopicError
from cadio.recordings.foxglove_mcap import (
    CALIBRATION,
    CAMERA_INFO_TOPIC,
    COLOR_TOPIC,
    DEPTH_TOPIC,
    FOXGLOVE,
    INSTANCE_TOPIC,
    RAW_IMAGE,
    TF_TOPIC,
    TRANSFORM,
)
from cadio.recordings.recording import (
    COLOUR_ENCODINGS,
    DEPTH_ENCODINGS,
    INSTANCE_ENCODINGS,
    Dialect,
    ImageMsg,
    Record,
)
from cadio.recordings.ros2_mcap import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    ROS2,
    TF_MESSAGE,
    TF_STATIC_TOPIC,
)

log = logging.getLogger(__name__)

DIALECTS = {d.message_encoding: d for d in (FOXGLOVE, ROS2)}
EXPECTED = {"image": f"{RAW_IMAGE} (protobuf) or {IMAGE} / {COMPRESSED_IMAGE} (cdr)",
             "calibration": f"{CALIBRATION} (protobuf) or {CAMERA_INFO} (cdr)",
             "tf": f"{TRANSFORM} (protobuf) or {TF_MESSAGE} (cdr)"}
# Our own topic names: whatever is logged there must be what the name promises.
_KNOWN = {COLOR_TOPIC: "image", DEPTH_TOPIC: "image", INSTANCE_TOPIC: "image",
          CAMERA_INFO_TOPIC: "calibration", TF_TOPIC: "tf", TF_STATIC_TOPIC: "tf"}
_ROLE_OF = {COLOR_TOPIC: "colour", DEPTH_TOPIC: "depth", INSTANCE_TOPIC: "instance"}
_WANTED = {"depth": "a depth image (16UC1, mono16 or 32FC1)",
           "colour": "a colour image (rgb8, bgr8, rgba8, bgra8, mono8, PNG or JPEG)",
           "instance": "instance ids (16UC1, mono16 or 32SC1)"}
_TRANSPORTS = ("compressed", "compressedDepth", "theora", "zstd")  # image_transport twins


def kind_of(schema: Any, channel: Any) -> str | None:
    dialect = DIALECTS.get(channel.message_encoding)
    if dialect is None or schema is None:
        return None
    return dialect.kinds.get(schema.name)


def preferred(channels: list[tuple[str, str | None]]) -> tuple[str | None, frozenset[str]]:
    """From the (topic, kind) of every channel: a depth topic registered to colour (drivers
    name it "aligned_depth..."), preferred over the raw depth such recordings also carry; and
    the compressed twins of raw image topics (``image_transport``), which are skipped."""
    images = {t for t, k in channels if k in ("image", "compressed")}
    twins = frozenset(t for t in images if t.rsplit("/", 1)[-1] in _TRANSPORTS
                      and t.rsplit("/", 1)[0] in images)
    aligned = sorted(t for t in images - twins if "aligned" in t and "depth" in t)
    return (aligned[0] if aligned else None), twins


def image_role(topic: str, img: ImageMsg) -> str | None:
    """What an image topic is to the reader: depth, colour, instance ids, or None (skipped:
    infrared, confidence, unknown encodings)."""
    t = topic.lower()
    if "instance" in t:
        return "instance" if img.encoding in INSTANCE_ENCODINGS else None
    if img.encoding == "mono16":  # RealSense's depth is mono16 in its own bags; so is 16-bit IR
        return "depth" if "depth" in t else None
    if img.encoding in DEPTH_ENCODINGS:
        return "depth"
    if img.encoding == "mono8" and not any(h in t for h in ("color", "colour", "rgb")):
        return None  # infrared streams are mono8 too
    return "colour" if img.encoding in COLOUR_ENCODINGS else None


@dataclass
class Channels:
    """Each channel's role, found from its schema (and first image), and its decoders."""

    path: Path
    depth_topic: str | None
    colour_topic: str | None
    twins: frozenset[str] = frozenset()
    roles: dict[int, str | None] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)  # image topic -> encoding
    dialects: dict[str, str] = field(default_factory=dict)  # used topic -> dialect name
    decoders: dict[str, Any] = field(
        default_factory=lambda: {e: d.decoders() for e, d in DIALECTS.items()})

    def records(self, schema: Any, channel: Any, message: Any) -> tuple[str, list[Record]] | None:
        """(role, records) of a message on a channel the reader uses, else None."""
        role = self.roles.get(channel.id, "")
        if role is None:
            return None
        kind = self._check(schema, channel) if role == "" else kind_of(schema, channel)
        if kind is None:
            self.roles[channel.id] = None
            return None
        dialect = DIALECTS[channel.message_encoding]
        try:
            recs = self._convert(dialect, kind, schema, channel, message)
        except CaptureTopicError as exc:
            if role or not self._optional(channel.topic):
                raise
            log.info("%s: %s; topic skipped", self.path, exc)  # e.g. RVL compressed depth
            self.skipped[channel.topic] = f"cannot decode: {exc.found}"
            self.roles[channel.id] = None
            return None
        if role == "":
            role = self.roles[channel.id] = self._assign(channel.topic, kind, recs)
            if role is not None:
                self.dialects[channel.topic] = dialect.name
        return None if role is None else (role, recs)

    def _optional(self, topic: str) -> bool:
        """Whether a topic may be skipped: not one of our names, not asked for."""
        return topic not in _KNOWN and topic not in (self.depth_topic, self.colour_topic)

    def _check(self, schema: Any, channel: Any) -> str | None:
        """The channel's kind; a known topic name holding something else is an error."""
        kind, expected = kind_of(schema, channel), _KNOWN.get(channel.topic)
        if expected is not None and (kind or "").replace("compressed", "image") != expected:
            name = schema.name if schema is not None else "no schema"
            raise CaptureTopicError(self.path, channel.topic,
                                    f"schema {name} ({channel.message_encoding})",
                                    EXPECTED[expected])
        return kind

    def _convert(self, dialect: Dialect, kind: str, schema: Any, channel: Any,
                 message: Any) -> list[Record]:
        try:
            decoder = self.decoders[channel.message_encoding].decoder_for(
                channel.message_encoding, schema)
            if decoder is None:
                raise ValueError(f"{schema.encoding or 'no'} schema encoding")
            return dialect.records(kind, channel.topic, decoder(message.data), message.log_time)
        except (DecodeError, McapError, TypeError, ValueError, AttributeError, IndexError,
                struct.error, UnicodeDecodeError) as exc:
            raise CaptureTopicError(self.path, channel.topic, f"cannot decode {schema.name} "
                                    f"({type(exc).__name__}: {exc})",
                                    EXPECTED[kind.replace("compressed", "image")]) from exc

    def _assign(self, topic: str, kind: str, recs: list[Record]) -> str | None:
        if kind in ("calibration", "tf"):
            return kind
        img = recs[0]
        assert isinstance(img, ImageMsg)
        role = image_role(topic, img)
        wanted = {"depth": self.depth_topic, "colour": self.colour_topic}
        asked = next((r for r, t in wanted.items() if t == topic), None)
        needed = _ROLE_OF.get(topic) or asked
        if needed is not None and role != needed:
            raise CaptureTopicError(self.path, topic, f"encoding {img.encoding!r}",
                                    _WANTED[needed])
        if role is None or (topic in self.twins and topic not in wanted.values()):
            self.skipped[topic] = img.encoding
            return None
        chosen = wanted.get(role)
        if chosen is not None and chosen != topic:
            log.info("%s: image topic %s not used (%s comes from %s)", self.path, topic, role,
                     chosen)
            self.skipped[topic] = img.encoding
            return None
        if role in wanted:
            setattr(self, f"{role}_topic", topic)
        return role

    def missing(self, role: str) -> CaptureTopicError:
        seen = ", ".join(f"{t} ({e})" for t, e in sorted(self.skipped.items())) or "none"
        return CaptureTopicError(self.path, None, f"no {role} image topic (images not used: "
                                 f"{seen})", f"{_WANTED[role]} on {EXPECTED['image']}")

"""ROS 2 recordings in MCAP read as our own captures: the same frames, real recordings' quirks,
colour from another sensor, compressed images, truncation, clear errors, and the capture stage
that ``mateqa nightly --captures`` runs."""

from __future__ import annotations

import io
import json
import struct
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from PIL import Image
from ros2_recording import (
    OPTICAL_IN_LINK,
    Recording,
    camera_info,
    header,
    image,
    ros2_recording,
    transform,
    write_ros2_capture,
)
from test_mcap_io import SMALL, pair

from cadio.camera.render import render_views, scene_meta
from cadio.capture.scan import ScanConfig, read_captures
from cadio.errors import CaptureTopicError, CaptureTruncatedError
from cadio.recordings.mcap_io import (
    DEPTH_M,
    read_capture,
    read_scene_meta,
    summarise_capture,
    write_capture,
)
from cadio.records import RgbdFrame
from cadio.workspace import Workspace, write_mesh
from flows.cli import main

T0 = 1_700_000_000 * 10**9
PERIOD = 33_333_333
ALIGNED = "/camera/aligned_depth_to_color/image_raw"
MM = 0.0005 + 1e-6  # rounding to 1 mm steps


def stamped(frames: list[RgbdFrame]) -> list[RgbdFrame]:
    return [replace(f, timestamp_ns=T0 + i * PERIOD) for i, f in enumerate(frames)]


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return stamped(list(render_views(pair(), SMALL)))


@pytest.fixture(scope="module")
def meta() -> dict:
    return scene_meta(pair(), SMALL, {"left": [["box-1", "cyl-2"]]})


def read_until_error(path: Path) -> tuple[list[RgbdFrame], Exception | None]:
    got: list[RgbdFrame] = []
    try:
        for f in read_capture(path):
            got.append(f)
    except (CaptureTopicError, CaptureTruncatedError) as exc:
        return got, exc
    return got, None


@pytest.mark.parametrize("encoding", ["16UC1", "mono16", "32FC1"])
def test_a_ros2_recording_reads_as_our_own_capture_of_the_same_views(
        tmp_path: Path, frames: list[RgbdFrame], meta: dict, encoding: str) -> None:
    ours, theirs = tmp_path / "ours.mcap", tmp_path / "ros2.mcap"
    write_capture(ours, frames, meta, depth_encoding=DEPTH_M if encoding == "32FC1" else "16UC1")
    write_ros2_capture(theirs, frames, scene=meta, depth_encoding=encoding)
    own, back = list(read_capture(ours)), list(read_capture(theirs))
    assert len(back) == len(own) == len(frames)
    for a, b in zip(own, back, strict=True):
        assert b.timestamp_ns == a.timestamp_ns and b.intrinsics == a.intrinsics
        assert np.array_equal(b.colour, a.colour)
        assert np.array_equal(b.depth, a.depth)  # both in the same units: no rounding apart
        assert b.instance is not None and np.array_equal(b.instance, a.instance)
        # the camera through world -> base_link (/tf) -> camera_link -> optical (/tf_static)
        assert b.world_to_camera == pytest.approx(a.world_to_camera, abs=1e-9)
        assert b.meta["dialect"] == "ROS 2" and a.meta["dialect"] == "Foxglove"
        assert b.meta["depth_topic"] == ALIGNED  # preferred over the raw depth topic
        assert (b.meta["pose_source"], b.meta["world_frame"], b.meta["gravity_source"]) == (
            "tf", "world", "tf")
        assert b.meta["colour"] == "registered" and b.meta["warnings"] == ()
        assert b.colour.flags.writeable and b.depth.flags.writeable
    for a, f in zip(back, frames, strict=True):
        assert np.max(np.abs(a.depth - f.depth)) <= (0.0 if encoding == "32FC1" else MM)
    assert read_scene_meta(theirs) == meta


def test_the_recording_is_ros2_cdr_to_an_independent_decoder(tmp_path: Path,
                                                             frames: list[RgbdFrame]) -> None:
    """The test recordings are what ROS 2 writes: another CDR implementation
    (mcap-ros2-support-fast) decodes every message with the schemas stored in the file."""
    fast = pytest.importorskip("mcap_ros2_support_fast")
    path = tmp_path / "ros2.mcap"
    write_ros2_capture(path, frames[:2])
    factory, topics = fast.DecoderFactory(), {}
    with path.open("rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "ros2"
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
            decoded = factory.decoder_for("cdr", schema)(message.data)
            topics[channel.topic] = decoded
    depth = topics[ALIGNED]
    assert (depth.encoding, depth.width, depth.height, depth.step) == ("16UC1", 320, 240, 640)
    assert topics["/camera/color/image_raw"].step == 320 * 3 + 8
    assert len(topics["/camera/color/camera_info"].k) == 9
    assert topics["/tf_static"].transforms[1].child_frame_id == "camera_color_optical_frame"


def test_a_truncated_ros2_recording_yields_its_complete_frames_then_fails(
        tmp_path: Path, frames: list[RgbdFrame]) -> None:
    path = tmp_path / "cut.mcap"
    write_ros2_capture(path, frames, chunk_size=64 * 1024)
    whole = list(read_capture(path))
    path.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.7)])
    got, err = read_until_error(path)
    assert isinstance(err, CaptureTruncatedError) and err.path == str(path)
    assert err.messages > 0 and "truncated or corrupt" in str(err)
    assert 1 <= len(got) < len(frames)
    for a, b in zip(whole, got, strict=False):
        assert b.timestamp_ns == a.timestamp_ns and np.array_equal(b.depth, a.depth)
        assert b.meta["depth_topic"] == ALIGNED  # found without the summary the cut removed
        assert b.world_to_camera == pytest.approx(a.world_to_camera, abs=1e-12)


def _realsense_bag(path: Path, frames: list[RgbdFrame], colour: list[RgbdFrame]) -> None:
    """A RealSense recording as its own ROS 1 bags hold it, converted to ROS 2 MCAP: depth
    labelled mono16 (1 mm units), colour from the other sensor (other size and intrinsics),
    frame ids "0" and no tf, log times from the epoch, and the sensor options, infrared, IMU
    and log topics nobody uses."""
    dev = "/device_0/sensor_0/Depth_0"
    rgb = "/device_0/sensor_1/Color_0"
    with ros2_recording(path, log_time=lambda ns: ns - T0) as rec:
        rec.put("/rosout", "rcl_interfaces/msg/Log", {"stamp": header(T0, "")["stamp"],
                                                      "level": 20, "msg": "start"}, T0)
        rec.put("/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32",
                {"data": 0.001}, T0)
        for f, c in zip(frames, colour, strict=True):
            ns = f.timestamp_ns
            mm = np.round(f.depth.astype(np.float64) * 1000).astype("<u2")
            rec.put(f"{dev}/info/camera_info", "sensor_msgs/msg/CameraInfo",
                    camera_info(ns, "0", f), ns)
            rec.put(f"{rgb}/info/camera_info", "sensor_msgs/msg/CameraInfo",
                    camera_info(ns + 3_000_000, "0", c), ns + 3_000_000)
            rec.put(f"{dev}/image/data", "sensor_msgs/msg/Image", image(ns, "0", mm, "mono16"),
                    ns)
            rec.put("/device_0/sensor_0/Infrared_1/image/data", "sensor_msgs/msg/Image",
                    image(ns, "0", np.zeros_like(mm, dtype=np.uint8), "mono8"), ns)
            rec.put(f"{rgb}/image/data", "sensor_msgs/msg/Image",
                    image(ns + 3_000_000, "0", c.colour, "rgb8"), ns + 3_000_000)
            rec.put("/device_0/sensor_2/Accel_0/imu/data", "sensor_msgs/msg/Imu",
                    {"header": header(ns, "0"),
                     "linear_acceleration": {"x": 0.0, "y": -9.81, "z": 0.0}}, ns)


def test_real_recording_quirks(tmp_path: Path, frames: list[RgbdFrame]) -> None:
    other = replace(SMALL, width=424, height=240, hfov_deg=69.4, noise=None)
    colour = stamped(list(render_views(pair(), other)))
    path = tmp_path / "realsense.mcap"
    _realsense_bag(path, frames, colour)
    back = list(read_capture(path))
    assert len(back) == len(frames)
    for f, b in zip(frames, back, strict=True):
        assert b.intrinsics == f.intrinsics  # the depth camera's, not the colour sensor's
        assert np.max(np.abs(b.depth - f.depth)) <= MM and b.instance is None
        assert b.meta["depth_topic"] == "/device_0/sensor_0/Depth_0/image/data"
        assert b.meta["colour_offset_ns"] == 3_000_000
        # other intrinsics and no transform between the sensors: colour left out, said so
        assert b.meta["colour"] == "left out" and not b.colour.any()
        assert b.meta["pose_source"] == "camera" and b.meta["gravity_source"] == "support plane"
        warnings = " ".join(b.meta["warnings"])
        assert "the camera is the world frame" in warnings and "colour left out" in warnings
        # the camera is the world frame, turned so that Z is the table's normal (up)
        assert np.array_equal(b.world_to_camera[:3, 3], np.zeros(3))
        angle = np.arccos(np.clip(b.world_to_camera[:3, 2] @ f.world_to_camera[:3, 2], -1, 1))
        assert np.degrees(angle) < 1.0


def test_without_tf_or_a_support_plane_the_camera_is_taken_level(
        tmp_path: Path, frames: list[RgbdFrame]) -> None:
    """A recording that sees no plane (a patch of depth only) and holds no tf: the camera is
    the world frame, up is the image's up, and both are said."""
    patch = np.zeros_like(frames[0].depth)
    patch[100:110, 150:160] = 1.2
    path = tmp_path / "patch.mcap"
    fid = "camera_color_optical_frame"
    with ros2_recording(path) as rec:
        for f in frames[:2]:
            ns = f.timestamp_ns
            rec.put("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo",
                    camera_info(ns, fid, f), ns)
            rec.put("/camera/color/image_raw", "sensor_msgs/msg/Image",
                    image(ns, fid, f.colour, "rgb8"), ns)
            rec.put("/camera/depth/image_raw", "sensor_msgs/msg/Image",
                    image(ns, fid, (patch * 1000).astype("<u2"), "16UC1"), ns)
    back = list(read_capture(path))
    assert len(back) == 2
    for b in back:
        assert b.meta["gravity_source"] == "level camera"
        assert any("a level camera" in w for w in b.meta["warnings"])
        # world +Z seen from the camera is the image's up (-y of the optical frame)
        assert b.world_to_camera[:3, 2] == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)


def test_colour_from_another_sensor_is_reprojected_with_the_recorded_extrinsic(
        tmp_path: Path, frames: list[RgbdFrame]) -> None:
    """Depth from one camera, colour from another (other intrinsics, 3 degrees round the
    scene); the tf tree holds both optical frames on the camera link. Re-projected through it,
    the colour matches what the depth camera itself saw; stretched to size without the
    extrinsic, it does not."""
    other = replace(SMALL, width=400, height=300, hfov_deg=58.0, start_deg=3.0, noise=None)
    colour = stamped(list(render_views(pair(), other)))
    depth_in_colour = colour[0].world_to_camera @ np.linalg.inv(frames[0].world_to_camera)
    colour_in_link = OPTICAL_IN_LINK @ np.linalg.inv(depth_in_colour)
    path = tmp_path / "two-sensors.mcap"
    with ros2_recording(path) as rec:
        rec.put("/tf_static", "tf2_msgs/msg/TFMessage", {"transforms": [
            transform(T0, "camera_link", "camera_depth_optical_frame", OPTICAL_IN_LINK),
            transform(T0, "camera_link", "camera_color_optical_frame", colour_in_link)]}, T0)
        for f, c in zip(frames, colour, strict=True):
            ns = f.timestamp_ns
            link = np.linalg.inv(f.world_to_camera) @ np.linalg.inv(OPTICAL_IN_LINK)
            rec.put("/tf", "tf2_msgs/msg/TFMessage",
                    {"transforms": [transform(ns, "world", "camera_link", link)]}, ns)
            for name, fr, frame_id in (("depth", f, "camera_depth_optical_frame"),
                                       ("color", c, "camera_color_optical_frame")):
                rec.put(f"/camera/{name}/camera_info", "sensor_msgs/msg/CameraInfo",
                        camera_info(ns, frame_id, fr), ns)
            mm = np.round(f.depth.astype(np.float64) * 1000).astype("<u2")
            rec.put("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image",
                    image(ns, "camera_depth_optical_frame", mm, "16UC1"), ns)
            rec.put("/camera/color/image_raw", "sensor_msgs/msg/Image",
                    image(ns, "camera_color_optical_frame", c.colour, "rgb8"), ns)
    back = list(read_capture(path))
    assert len(back) == len(frames)
    for f, c, b in zip(frames, colour, back, strict=True):
        assert b.meta["colour"] == "reprojected" and b.meta["warnings"] == ()
        assert b.intrinsics == f.intrinsics
        assert b.world_to_camera == pytest.approx(f.world_to_camera, abs=1e-9)
        seen = b.depth > 0
        painted = seen & b.colour.any(axis=2)
        assert painted.sum() >= 0.95 * seen.sum()
        parts = painted & (f.instance > 0)  # the table is one colour: judge on the parts
        assert _agreement(b.colour, f.colour, parts) >= 0.9
        stretched = np.asarray(Image.fromarray(c.colour).resize(f.colour.shape[1::-1]))
        assert _agreement(stretched, f.colour, parts) < 0.7


def _agreement(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Share of the mask's pixels whose colours differ by at most 12 levels in every channel."""
    close = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) <= 12
    return float(close[mask].mean())


def _png(pixels: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def _jpeg(pixels: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="JPEG", quality=95)
    return buf.getvalue()


def _compressed_depth(mm: np.ndarray) -> bytes:
    """image_transport's compressedDepth payload of 16UC1 depth: a 12-byte header, a PNG."""
    return struct.pack("<i2f", 0, 0.0, 0.0) + _png(mm.astype(np.uint16))


def _inverse_depth(metres: np.ndarray) -> bytes:
    """compressedDepth of 32FC1: q = A / depth + B as a 16-bit PNG (A, B for 100 levels and a
    10 m range, the transport's defaults)."""
    a = 100.0 * 101.0
    b = 1.0 - a / 10.0
    q = np.where(metres > 0, a / np.where(metres > 0, metres, 1.0) + b, 0.0)
    return struct.pack("<i2f", 0, a, b) + _png(q.astype(np.uint16))


@pytest.mark.parametrize(("fmt", "encode", "colour_atol"),
                         [("rgb8; png compressed rgb8", _png, 0), ("jpeg", _jpeg, 24)])
def test_compressed_images_read(tmp_path: Path, frames: list[RgbdFrame], fmt: str,
                                encode: Callable[[np.ndarray], bytes], colour_atol: int) -> None:
    """Colour as CompressedImage (PNG exact, JPEG close) and depth through compressedDepth
    (16UC1 exact; 32FC1 as quantised inverse depth within a millimetre), beside raw topics
    whose compressed twins are skipped."""
    path = tmp_path / "compressed.mcap"
    fid, compressed = "camera_color_optical_frame", "sensor_msgs/msg/CompressedImage"
    in_metres = "/camera/depth_m/image_raw/compressedDepth"
    with ros2_recording(path) as rec:
        for f in frames:
            ns = f.timestamp_ns
            mm = np.round(f.depth.astype(np.float64) * 1000).astype(np.uint16)
            rec.put("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo",
                    camera_info(ns, fid, f), ns)
            rec.put("/camera/color/image_raw/compressed", compressed,
                    {"header": header(ns, fid), "format": fmt, "data": encode(f.colour)}, ns)
            rec.put("/camera/depth/image_raw/compressedDepth", compressed,
                    {"header": header(ns, fid), "format": "16UC1; compressedDepth png",
                     "data": _compressed_depth(mm)}, ns)
            rec.put(in_metres, compressed, {"header": header(ns, fid), "format":
                                            "32FC1; compressedDepth png",
                                            "data": _inverse_depth(f.depth)}, ns)
            rec.put("/camera/depth_png/image_raw/compressed", compressed,
                    {"header": header(ns, fid), "format": "16UC1; png compressed 16UC1",
                     "data": _png(mm)}, ns)
    back = list(read_capture(path))
    metres = list(read_capture(path, depth_topic=in_metres))
    png = list(read_capture(path, depth_topic="/camera/depth_png/image_raw/compressed"))
    assert len(back) == len(metres) == len(png) == len(frames)
    for f, b, m, p in zip(frames, back, metres, png, strict=True):
        assert np.max(np.abs(b.depth - f.depth)) <= MM and np.array_equal(p.depth, b.depth)
        assert np.max(np.abs(m.depth - f.depth)) <= 0.001 and np.array_equal(m.depth > 0,
                                                                              f.depth > 0)
        diff = np.abs(b.colour.astype(np.int16) - f.colour.astype(np.int16))
        assert np.percentile(diff, 99) <= colour_atol and diff.mean() <= colour_atol / 10


def test_compressed_twins_and_undecodable_topics_are_skipped(tmp_path: Path,
                                                            frames: list[RgbdFrame]) -> None:
    """The compressed twin of a raw topic, and a topic in a codec the reader lacks (RVL
    compressed depth) that nobody asked for, are skipped; asked for, the codec is an error."""
    def others(rec: Recording, ns: int, f: RgbdFrame) -> None:
        fid, compressed = "camera_color_optical_frame", "sensor_msgs/msg/CompressedImage"
        rec.put("/camera/color/image_raw/compressed", compressed,
                {"header": header(ns, fid), "format": "jpeg",
                 "data": _jpeg(np.zeros_like(f.colour))}, ns)
        rec.put("/camera/depth/rvl", compressed, {"header": header(ns, fid), "format":
                                                  "16UC1; compressedDepth rvl",
                                                  "data": b"\0" * 12 + b"RVL"}, ns)

    path = tmp_path / "twins.mcap"
    write_ros2_capture(path, frames[:2], extra=[others])
    back = list(read_capture(path))
    assert {b.meta["colour_topic"] for b in back} == {"/camera/color/image_raw"}
    assert all(np.array_equal(b.colour, f.colour) for b, f in zip(back, frames, strict=False))
    with pytest.raises(CaptureTopicError) as err:
        list(read_capture(path, depth_topic="/camera/depth/rvl"))
    assert err.value.topic == "/camera/depth/rvl" and "cannot decode" in err.value.found


def _topics_only(path: Path, frames: list[RgbdFrame], topics: dict[str, tuple[str, Callable]]
                 ) -> None:
    with ros2_recording(path) as rec:
        for f in frames:
            for topic, (datatype, make) in topics.items():
                rec.put(topic, datatype, make(f.timestamp_ns, f), f.timestamp_ns)


def test_an_unknown_encoding_or_a_missing_topic_names_file_topic_and_expectation(
        tmp_path: Path, frames: list[RgbdFrame]) -> None:
    fid = "camera_color_optical_frame"
    info = ("sensor_msgs/msg/CameraInfo", lambda ns, f: camera_info(ns, fid, f))
    mm = ("sensor_msgs/msg/Image", lambda ns, f: image(
        ns, fid, np.round(f.depth * 1000).astype("<u2"), "16UC1"))
    infrared = ("sensor_msgs/msg/Image", lambda ns, f: image(
        ns, fid, np.zeros(f.depth.shape, np.uint8), "mono8"))
    yuv = ("sensor_msgs/msg/Image", lambda ns, f: image(ns, fid, f.colour[..., :2], "yuv422"))

    no_colour = tmp_path / "no-colour.mcap"
    _topics_only(no_colour, frames[:2], {"/camera/color/camera_info": info,
                                         "/camera/depth/image_rect_raw": mm,
                                         "/camera/infra1/image_rect_raw": infrared})
    with pytest.raises(CaptureTopicError) as err:
        list(read_capture(no_colour))
    e = err.value
    assert e.path == str(no_colour) and e.topic is None and str(no_colour) in str(e)
    assert "no colour image topic" in e.found
    assert "/camera/infra1/image_rect_raw (mono8)" in e.found
    assert "rgb8" in e.expected and "sensor_msgs/msg/Image" in e.expected

    bad = tmp_path / "yuv-depth.mcap"
    _topics_only(bad, frames[:1], {"/camera/color/camera_info": info,
                                   "/camera/depth/image_raw": yuv})
    with pytest.raises(CaptureTopicError) as err:
        list(read_capture(bad))
    assert err.value.topic == "/camera/depth/image_raw" and "yuv422" in err.value.found
    assert "16UC1" in err.value.expected

    wrong_schema = tmp_path / "tf-as-string.mcap"
    _topics_only(wrong_schema, frames[:1], {"/tf": ("std_msgs/msg/String",
                                                    lambda ns, f: {"data": "x"})})
    with pytest.raises(CaptureTopicError) as err:
        list(read_capture(wrong_schema))
    assert err.value.topic == "/tf" and "std_msgs/msg/String" in err.value.found
    assert "tf2_msgs/msg/TFMessage" in err.value.expected


def test_an_idl_schema_is_named_as_undecodable(tmp_path: Path) -> None:
    path = tmp_path / "idl.mcap"
    with path.open("wb") as fh:
        w = McapWriter(fh)
        w.start(profile="ros2", library="test")
        sid = w.register_schema("sensor_msgs/msg/Image", "ros2idl", b"module sensor_msgs {};")
        cid = w.register_channel("/camera/color/image_raw", "cdr", sid)
        w.add_message(cid, log_time=1, data=b"\x00\x01\x00\x00", publish_time=1)
        w.finish()
    with pytest.raises(CaptureTopicError, match="/camera/color/image_raw") as err:
        list(read_capture(path))
    assert "ros2idl" in err.value.found and "sensor_msgs/msg/Image" in err.value.expected


def test_capture_read_prints_what_was_read(tmp_path: Path, frames: list[RgbdFrame],
                                          capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "ros2.mcap"
    write_ros2_capture(path, frames)
    assert main(["capture", "--read", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == len(frames) and out["dialect"] == "ROS 2"
    assert out["depth_topic"] == ALIGNED and out["pose_source"] == "tf"
    assert out["intrinsics"]["width"] == 320 and out["error"] == ""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-2000])
    assert main(["capture", "--read", str(cut)]) == 2
    out = json.loads(capsys.readouterr().out)
    assert "truncated" in out["error"] and out["frames"] >= 1
    assert summarise_capture(path).frames == len(frames)


def recordings_of_the_pair(tmp_path: Path) -> tuple[Workspace, Path]:
    """A workspace that knows the parts of ``pair()``, and an empty folder for recordings."""
    ws = Workspace(tmp_path / "ws")
    for part in pair():
        write_mesh(ws.mesh(part.part_id), part.mesh)
    folder = tmp_path / "recordings"
    folder.mkdir()
    return ws, folder


def test_the_nightly_capture_stage_reads_ros2_recordings(tmp_path: Path,
                                                        frames: list[RgbdFrame],
                                                        meta: dict) -> None:
    """``nightly --captures DIR``'s stage: a ROS 2 recording with instance ids and a scene
    gives each part's observed points; a real one (no ids, no scene, no tf) gives its frames
    and clusters but no part to score, with its warnings; a bad one is reported and the others
    go on."""
    ws, folder = recordings_of_the_pair(tmp_path)
    write_ros2_capture(folder / "sim.mcap", frames, scene=meta)
    colour = stamped(list(render_views(pair(), replace(SMALL, width=424, hfov_deg=69.4))))
    _realsense_bag(folder / "real.mcap", frames, colour)
    _topics_only(folder / "bad.mcap", frames[:1], {"/camera/depth/image_raw": (
        "sensor_msgs/msg/Image", lambda ns, f: image(ns, "x", f.colour, "rgb8"))})
    cfg = ScanConfig(views_per_scene=8, n_in=32, n_out=32, lengths=(2,))
    got = {s.scene_id: s for s in read_captures(folder, ws, cfg)}
    assert set(got) == {"sim", "real", "bad"}
    assert "/camera/depth/image_raw" in got["bad"].error and "16UC1" in got["bad"].error
    assert got["sim"].error == "" and got["sim"].frames == len(frames)
    assert got["sim"].input_parts == 2 and got["sim"].warnings == ()
    for part in pair():
        with np.load(ws.inputs("sim", part.instance_id) / "points.npz") as z:
            assert z["points"].shape[1:] == (600, 3) and len(z["view"]) >= 1
            # observed points of the part lie in its world box (the tf chain's world)
            lo, hi = _world_box(meta, part.part_id, part.mesh.vertices)
            pts = z["points"].reshape(-1, 3)
            assert np.mean(np.all((pts >= lo - 0.01) & (pts <= hi + 0.01), axis=1)) >= 0.95
    real = got["real"]
    assert real.error == "" and real.frames == len(frames) and real.input_parts == 0
    assert any("world frame" in w for w in real.warnings)
    assert np.isnan(real.seg_mean_iou)


def _world_box(meta: dict, part_id: str, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    part = next(p for p in meta["parts"] if p["part_id"] == part_id)
    scale = meta["scale_m_per_mm"]
    pose = np.asarray(part["pose_mm"])
    world = (vertices @ pose[:3, :3].T + pose[:3, 3]) * scale
    return world.min(axis=0), world.max(axis=0)


# ---------------------------------------------------------------- recordings the stages cannot use


def _frames_with(frames: list[RgbdFrame], **changes: object) -> list[RgbdFrame]:
    return [replace(f, **changes) for f in frames]  # type: ignore[arg-type]


def _nan_pose(path: Path, frames: list[RgbdFrame], meta: dict) -> None:
    """Our own dialect, with NaN in the camera's transform."""
    import cadio.recordings.foxglove_mcap as foxglove

    whole = foxglove._transform

    def nan(stamp: object, world_to_camera: np.ndarray) -> object:
        msg = whole(stamp, world_to_camera)  # type: ignore[arg-type]
        msg.translation.x = float("nan")
        return msg

    foxglove._transform = nan  # type: ignore[assignment]
    try:
        write_capture(path, frames, meta)
    finally:
        foxglove._transform = whole


def _png_bomb(path: Path, frames: list[RgbdFrame], meta: dict) -> None:
    """Colour as a PNG that declares 20000 x 20000 pixels (a few kB on disk)."""
    buf = io.BytesIO()
    Image.new("L", (20000, 20000)).save(buf, format="PNG")
    with ros2_recording(path) as rec:
        for f in frames:
            ns = f.timestamp_ns
            rec.put("/camera/camera_info", "sensor_msgs/msg/CameraInfo", camera_info(ns, "c", f),
                    ns)
            rec.put("/camera/depth/image_raw", "sensor_msgs/msg/Image",
                    image(ns, "c", np.round(f.depth * 1000).astype("<u2"), "16UC1"), ns)
            rec.put("/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
                    {"header": header(ns, "c"), "format": "png", "data": buf.getvalue()}, ns)


def _one_pixel(frame: RgbdFrame) -> RgbdFrame:
    k = replace(frame.intrinsics, width=1, height=1, cx=0.0, cy=0.0)
    return replace(frame, intrinsics=k, colour=frame.colour[:1, :1].copy(),
                   depth=frame.depth[:1, :1].copy(), instance=None)


# (how the bad recording is written, the words its error must hold)
BAD_RECORDINGS: dict[str, tuple[Callable[[Path, list[RgbdFrame], dict], None], list[str]]] = {
    "a focal length of 0": (lambda p, fs, m: write_ros2_capture(p, _frames_with(
        fs, intrinsics=replace(fs[0].intrinsics, fx=0.0)), scene=m),
        ["camera_info", "fx=0", "focal lengths above 0"]),
    "NaN in the camera pose": (_nan_pose, ["camera pose", "not finite"]),
    "a PNG declaring 20000x20000 pixels": (_png_bomb, ["compressed", "more pixels"]),
    "all-zero depth": (lambda p, fs, m: write_ros2_capture(p, _frames_with(
        fs, depth=np.zeros_like(fs[0].depth)), scene=m), ["depth images are empty"]),
    "1x1 images": (lambda p, fs, m: write_capture(p, [_one_pixel(f) for f in fs], m),
                   ["1x1 pixels", "32 to 16384 pixels a side"]),
    "an MCAP header and nothing else": (lambda p, fs, m: p.write_bytes(
        b"\x89MCAP0\r\n\x01" + struct.pack("<QII", 8, 0, 0)), ["ends after 25 bytes"]),
}


@pytest.mark.parametrize("case", BAD_RECORDINGS)
def test_one_bad_recording_is_named_and_the_good_one_beside_it_is_scored(
        tmp_path: Path, frames: list[RgbdFrame], meta: dict, case: str) -> None:
    write, named = BAD_RECORDINGS[case]
    ws, folder = recordings_of_the_pair(tmp_path)
    write_ros2_capture(folder / "good.mcap", frames, scene=meta)
    write(folder / "bad.mcap", frames, meta)
    cfg = ScanConfig(views_per_scene=8, n_in=32, n_out=32, lengths=(2,))
    got = {s.scene_id: s for s in read_captures(folder, ws, cfg)}
    assert got["good"].error == "" and got["good"].input_parts == 2
    for word in named:
        assert word in got["bad"].error, got["bad"].error
    assert "Errno" not in got["bad"].error


def test_a_depth_image_without_a_measured_pixel_is_skipped_with_a_warning(
        tmp_path: Path, frames: list[RgbdFrame], meta: dict) -> None:
    """A sensor starting up sends empty depth first: those frames go, the others are read."""
    path = tmp_path / "warming-up.mcap"
    write_capture(path, [replace(frames[0], depth=np.zeros_like(frames[0].depth)), *frames[1:]],
                  meta)
    back = list(read_capture(path))
    assert len(back) == len(frames) - 1
    assert any("without a measured pixel" in w for w in back[-1].meta["warnings"])


def test_whatever_else_breaks_a_recording_is_named_and_the_night_goes_on(
        tmp_path: Path, frames: list[RgbdFrame], meta: dict,
        monkeypatch: pytest.MonkeyPatch) -> None:
    import cadio.capture.scan as scan

    ws, folder = recordings_of_the_pair(tmp_path)
    for name in ("a", "b"):
        write_ros2_capture(folder / f"{name}.mcap", frames, scene=meta)
    scanned = scan.scan_inputs

    def fragile(path: Path, *args: object, **kwargs: object) -> object:
        if path.stem == "a":  # a check the reader has not thought of yet
            raise IndexError("index 2 is out of bounds for axis 0 with size 0")
        return scanned(path, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(scan, "scan_inputs", fragile)
    cfg = ScanConfig(views_per_scene=8, n_in=32, n_out=32, lengths=(2,))
    got = {s.scene_id: s for s in read_captures(folder, ws, cfg)}
    assert got["a"].error == "IndexError: index 2 is out of bounds for axis 0 with size 0"
    assert got["b"].error == "" and got["b"].input_parts == 2

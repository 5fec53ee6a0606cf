"""Tests of cadio.recordings.mcap_io: exact round trips, independent readers, bad files."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.writer import Writer as ProtobufWriter

from cadio.camera.noise import NoiseConfig
from cadio.camera.render import CaptureConfig, PlacedPart, render_views, scene_meta
from cadio.errors import CaptureError, CaptureTopicError
from cadio.recordings.mcap_io import (
    CAMERA_INFO_TOPIC,
    COLOR_TOPIC,
    DEPTH_M,
    DEPTH_TOPIC,
    INSTANCE_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    CaptureWriter,
    read_capture,
    read_scene_meta,
    write_capture,
)
from cadio.records import Mesh, RgbdFrame

READER_DIR = Path(__file__).parent / "mcap_reader"
PYMCAP_CLI = Path(sys.executable).parent / "pymcap-cli"
SMALL = CaptureConfig(n_views=4, step_deg=30.0, width=320, height=240, noise=NoiseConfig())


def _mesh(m: o3d.geometry.TriangleMesh) -> Mesh:
    return Mesh(np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64))


def pair() -> list[PlacedPart]:
    box = o3d.geometry.TriangleMesh.create_box(100, 80, 60).translate((-50, -40, -30))
    cyl = o3d.geometry.TriangleMesh.create_cylinder(30, 120, resolution=32)
    a, b = np.eye(4), np.eye(4)
    a[:3, 3], b[:3, 3] = (-90, 0, 30), (90, 10, 60)
    return [PlacedPart(1, _mesh(box), a, "#c03030", "box-1", "box"),
            PlacedPart(2, _mesh(cyl), b, "#3050c0", "cyl-2", "cylinder")]


@pytest.fixture(scope="module")
def frames() -> list[RgbdFrame]:
    return list(render_views(pair(), SMALL))


@pytest.fixture(scope="module")
def meta() -> dict:
    return scene_meta(pair(), SMALL, {"left": [["box-1", "cyl-2"]]})


@pytest.fixture()
def capture(tmp_path: Path, frames: list[RgbdFrame], meta: dict) -> Path:
    path = tmp_path / "scene.mcap"
    write_capture(path, frames, meta)
    return path


def _stamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 10**9, nanos=ns % 10**9)


def _image(ns: int, frame_id: str, pixels: np.ndarray, encoding: str, pad: int = 0) -> RawImage:
    rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
    padded = np.zeros((rows.shape[0], rows.shape[1] + pad), dtype=np.uint8)
    padded[:, : rows.shape[1]] = rows
    return RawImage(timestamp=_stamp(ns), frame_id=frame_id, width=pixels.shape[1],
                    height=pixels.shape[0], encoding=encoding, step=padded.shape[1],
                    data=padded.tobytes())


def _calibration(ns: int, frame_id: str, frame: RgbdFrame) -> CameraCalibration:
    k = frame.intrinsics
    return CameraCalibration(timestamp=_stamp(ns), frame_id=frame_id, width=k.width,
                             height=k.height, distortion_model="plumb_bob", D=[0.0] * 5,
                             K=[k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1])


def write_foreign_recording(path: Path, frames: list[RgbdFrame], calibration: bool = True,
                            depth_topic: str = "/camera/depth/image_rect_raw",
                            sensor_streams: bool = False) -> None:
    """A recording as a real RGB-D camera driver would log it, with the plain mcap + Foxglove
    protobuf writer: bgr8 colour with padded rows, aligned 16UC1 depth 4 ms after each colour
    image, colour camera info, an unrelated log topic, no instance ids, no /tf, no scene; plus
    one colour image without depth first and one depth image without colour last.
    ``sensor_streams`` adds, first, what RealSense drivers also log: the unregistered depth
    (half size, on /camera/depth/image_rect_raw) and a mono8 infrared stream."""
    fid, t0, period = "camera_color_optical_frame", 1_700_000_000 * 10**9, 33_333_333
    with path.open("wb") as fh, ProtobufWriter(fh) as w:
        w.write_message("/rosout", Log(timestamp=_stamp(t0), message="start"), t0, t0)
        lead = frames[0].colour[..., ::-1].copy()
        w.write_message(COLOR_TOPIC, _image(t0 - period, fid, lead, "bgr8", 8), t0 - period)
        for i, f in enumerate(frames):
            tc, td = t0 + i * period, t0 + i * period + 4_000_000
            if calibration:
                w.write_message(CAMERA_INFO_TOPIC, _calibration(tc, fid, f), tc, tc)
            if sensor_streams:
                raw = np.zeros((f.depth.shape[0] // 2, f.depth.shape[1] // 2), dtype="<u2")
                ir = np.zeros(f.depth.shape, dtype=np.uint8)
                w.write_message("/camera/depth/image_rect_raw", _image(td, "depth", raw, "16UC1"),
                                td, td)
                w.write_message("/camera/infra1/image_rect_raw", _image(td, "ir", ir, "mono8"),
                                td, td)
            bgr = np.ascontiguousarray(f.colour[..., ::-1])
            w.write_message(COLOR_TOPIC, _image(tc, fid, bgr, "bgr8", 8), tc, tc)
            mm = np.round(f.depth.astype(np.float64) * 1000).astype("<u2")
            w.write_message(depth_topic, _image(td, fid, mm, "16UC1"), td, td)
        tl = t0 + len(frames) * period + 4_000_000
        w.write_message(depth_topic, _image(tl, fid, mm, "16UC1"), tl, tl)


def _read_until_error(path: Path) -> tuple[list[RgbdFrame], CaptureError | None]:
    got: list[RgbdFrame] = []
    try:
        for f in read_capture(path):
            got.append(f)
    except CaptureError as exc:
        return got, exc
    return got, None


def assert_same(a: RgbdFrame, b: RgbdFrame, depth_atol: float) -> None:
    assert b.timestamp_ns == a.timestamp_ns and b.intrinsics == a.intrinsics
    assert np.array_equal(b.colour, a.colour)
    assert np.array_equal(b.depth > 0, a.depth > 0)
    assert np.max(np.abs(b.depth - a.depth)) <= depth_atol
    assert b.instance is not None and np.array_equal(b.instance, a.instance)
    assert b.world_to_camera == pytest.approx(a.world_to_camera, abs=1e-12)


def test_round_trip_16uc1_is_exact_to_the_millimetre(capture: Path, frames: list[RgbdFrame],
                                                      meta: dict) -> None:
    back = list(read_capture(capture))
    assert len(back) == len(frames)
    for a, b in zip(frames, back, strict=True):
        assert_same(a, b, depth_atol=0.0005 + 1e-6)  # rounding to 1 mm steps
        assert b.depth.dtype == np.float32 and b.instance.dtype == np.int32
    assert read_scene_meta(capture) == meta


def test_round_trip_32fc1_is_exact(tmp_path: Path, frames: list[RgbdFrame]) -> None:
    path = tmp_path / "metres.mcap"
    write_capture(path, frames, depth_encoding=DEPTH_M)
    for a, b in zip(frames, read_capture(path), strict=True):
        assert_same(a, b, depth_atol=0.0)
    assert read_scene_meta(path) is None


def test_writer_is_atomic(tmp_path: Path, frames: list[RgbdFrame]) -> None:
    path = tmp_path / "broken.mcap"
    with pytest.raises(RuntimeError), CaptureWriter(path) as w:
        w.write_frame(frames[0])
        raise RuntimeError("renderer died")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError), CaptureWriter(path) as w:
        w.write_frame(replace(frames[0], instance=np.full((240, 320), 70000, dtype=np.int32)))


@pytest.mark.skipif(not PYMCAP_CLI.exists(), reason="pymcap-cli is not installed in the venv")
def test_pymcap_cli_doctor_accepts_the_file(capture: Path) -> None:
    done = subprocess.run([str(PYMCAP_CLI), "doctor", str(capture)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def test_node_mcap_libraries_read_and_decode_the_file(capture: Path,
                                                      frames: list[RgbdFrame]) -> None:
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    if not (READER_DIR / "node_modules" / "@mcap" / "core").is_dir():
        pytest.skip(f"run `npm ci --prefix {READER_DIR}` to install the independent reader")
    done = subprocess.run(["node", str(READER_DIR / "read.mjs"), str(capture)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    n = len(frames)
    assert out["topics"] == {COLOR_TOPIC: n, DEPTH_TOPIC: n, INSTANCE_TOPIC: n,
                             CAMERA_INFO_TOPIC: n, TF_TOPIC: n, SCENE_TOPIC: 1}
    assert out["schemas"][DEPTH_TOPIC] == "foxglove.RawImage"
    assert out["schemas"][TF_TOPIC] == "foxglove.FrameTransform"
    assert out["decoded"][DEPTH_TOPIC]["encoding"] == "16UC1"
    assert out["decoded"][COLOR_TOPIC] == {"width": 320, "height": 240, "encoding": "rgb8",
                                           "step": 960, "frame_id": "camera"}
    assert out["decoded"][CAMERA_INFO_TOPIC]["width"] == 320 and out["summary"] is True


def test_truncated_file_yields_complete_frames_then_fails(tmp_path: Path,
                                                          frames: list[RgbdFrame]) -> None:
    path = tmp_path / "cut.mcap"
    with CaptureWriter(path, chunk_size=64 * 1024) as w:
        for f in frames:
            w.write_frame(f)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.7)])
    got, err = _read_until_error(path)
    assert err is not None and "truncated or corrupt" in str(err) and str(path) in str(err)
    assert 1 <= len(got) < len(frames)
    for a, b in zip(frames, got, strict=False):
        assert_same(a, b, depth_atol=0.0005 + 1e-6)
    if PYMCAP_CLI.exists():
        done = subprocess.run([str(PYMCAP_CLI), "doctor", str(path)], capture_output=True,
                              timeout=120)
        assert done.returncode != 0


def test_corrupt_chunk_yields_frames_before_it_then_fails(tmp_path: Path,
                                                          frames: list[RgbdFrame]) -> None:
    path = tmp_path / "flipped.mcap"
    with CaptureWriter(path, chunk_size=64 * 1024) as w:
        for f in frames:
            w.write_frame(f)
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    path.write_bytes(bytes(data))
    got, err = _read_until_error(path)
    assert err is not None and 1 <= len(got) < len(frames)
    for a, b in zip(frames, got, strict=False):
        assert_same(a, b, depth_atol=0.0005 + 1e-6)


def test_scene_meta_survives_truncation(tmp_path: Path, capture: Path, meta: dict) -> None:
    cut = tmp_path / "cut-scene.mcap"
    data = capture.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert read_scene_meta(cut) == meta


def test_wrong_schema_on_a_known_topic_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "wrong.mcap"
    with path.open("wb") as fh, ProtobufWriter(fh) as w:
        w.write_message(DEPTH_TOPIC, CompressedImage(format="png", data=b"x"), 1, 1)
    with pytest.raises(CaptureError, match=DEPTH_TOPIC):
        list(read_capture(path))


def test_missing_calibration_is_rejected(tmp_path: Path, frames: list[RgbdFrame]) -> None:
    path = tmp_path / "nocalib.mcap"
    write_foreign_recording(path, frames[:2], calibration=False, depth_topic=DEPTH_TOPIC)
    with pytest.raises(CaptureTopicError, match=DEPTH_TOPIC) as err:
        list(read_capture(path))
    assert err.value.topic == DEPTH_TOPIC and "foxglove.CameraCalibration" in err.value.expected
    assert err.value.path == str(path) and "320x240" in err.value.found


def test_foreign_recording_without_ids_or_labels_reads(tmp_path: Path,
                                                        frames: list[RgbdFrame]) -> None:
    path = tmp_path / "realsense.mcap"
    write_foreign_recording(path, frames)
    given = np.eye(4)
    given[:3, 3] = (0.1, 0.2, 0.3)
    back = list(read_capture(path, pose=given))
    # the lone colour image pairs with nothing; the lone depth image keeps its frame, without
    # colour, and the reader says so
    assert len(back) == len(frames) + 1
    lone = back[-1]
    assert lone.meta["colour"] == "none" and not lone.colour.any()
    assert np.isfinite(lone.depth).any()
    assert any("without a colour image within" in w for w in lone.meta["warnings"])
    for a, b in zip(frames, back[:-1], strict=True):
        assert b.instance is None and b.intrinsics == a.intrinsics
        assert np.array_equal(b.colour, a.colour)
        assert np.max(np.abs(b.depth - a.depth)) <= 0.0005 + 1e-6
        assert np.array_equal(b.world_to_camera, given)
        assert b.meta["depth_topic"] == "/camera/depth/image_rect_raw"
        assert b.meta["colour_offset_ns"] == -4_000_000 and b.meta["pose_source"] == "given"
    assert read_scene_meta(path) is None
    # Without a pose or a transform, the camera is the world frame (and each frame says so),
    # turned so that world Z is the table's normal: the up the renderer's world has.
    own = next(read_capture(path))
    assert own.meta["pose_source"] == "camera" and own.meta["gravity_source"] == "support plane"
    assert any("the camera is the world frame" in w for w in own.meta["warnings"])
    assert np.array_equal(own.world_to_camera[:3, 3], np.zeros(3))
    up_true = frames[0].world_to_camera[:3, 2]  # world +Z in camera coordinates
    assert np.degrees(np.arccos(own.world_to_camera[:3, 2] @ up_true)) < 1.0


def test_colour_stamped_a_frame_apart_never_loses_the_depth(tmp_path: Path,
                                                             frames: list[RgbdFrame]) -> None:
    """As a D435 logs it: one colour image 101 ms before two depth images. The depth is read,
    without colour, with a warning; colour 30 ms off (under a frame period) still pairs."""
    fid, t0 = "camera_color_optical_frame", 1_700_000_000 * 10**9
    path = tmp_path / "d435.mcap"
    f = frames[0]
    mm = np.round(f.depth.astype(np.float64) * 1000).astype("<u2")
    with path.open("wb") as fh, ProtobufWriter(fh) as w:
        w.write_message(CAMERA_INFO_TOPIC, _calibration(t0, fid, f), t0, t0)
        w.write_message(COLOR_TOPIC, _image(t0, fid, np.ascontiguousarray(f.colour[..., ::-1]),
                                            "bgr8"), t0, t0)
        for dt in (101_000_000, 120_000_000):
            w.write_message(DEPTH_TOPIC, _image(t0 + dt, fid, mm, "16UC1"), t0 + dt, t0 + dt)
        late = t0 + 150_000_000
        w.write_message(COLOR_TOPIC, _image(late, fid, np.ascontiguousarray(f.colour[..., ::-1]),
                                            "bgr8"), late, late)
    back = list(read_capture(path, pose=np.eye(4)))
    assert len(back) == 2
    assert back[0].meta["colour"] == "none" and not back[0].colour.any()
    assert np.max(np.abs(back[0].depth - f.depth)) <= 0.0005 + 1e-6
    assert any("without a colour image" in w for w in back[0].meta["warnings"])
    assert back[1].meta["colour_offset_ns"] == 30_000_000  # within a frame period (34 ms)
    assert np.array_equal(back[1].colour, f.colour)


def test_registered_depth_is_preferred_and_infrared_ignored(tmp_path: Path,
                                                            frames: list[RgbdFrame]) -> None:
    path = tmp_path / "realsense-all-streams.mcap"
    aligned = "/camera/aligned_depth_to_color/image_raw"
    write_foreign_recording(path, frames, depth_topic=aligned, sensor_streams=True)
    back = list(read_capture(path))[:-1]  # the last depth image has no colour (above)
    assert len(back) == len(frames)
    assert {f.meta["depth_topic"] for f in back} == {aligned}
    assert {f.meta["colour_topic"] for f in back} == {COLOR_TOPIC}
    for a, b in zip(frames, back, strict=True):
        assert np.max(np.abs(b.depth - a.depth)) <= 0.0005 + 1e-6

"""Benchmark of reading recordings: our Foxglove captures against ROS 2 recordings of the views.

Renders a pair scene (``bench/speed/capture.py``'s, the paper's 640x480 camera, noise on) and writes
the views twice: as our capture (``write_capture``: Foxglove protobuf, 16UC1 depth, instance ids)
and as a robot's ROS 2 recording (``tests/ros2_recording.py``: CDR, a tf chain, registered and
raw depth, camera infos, instance ids). Then reads each with ``read_capture`` and, as floors, with
the bare ``mcap`` reader (chunks decompressed, messages not decoded), and times the CDR decoding
of the recording's messages by Foxglove's ``mcap_ros2`` (what the reader uses) and by
``mcap_ros2_support_fast`` (when installed). Best of the repeats; frames per second of wall
time. Runs in about half a minute.

Usage: ``.venv/bin/python bench/speed/recordings.py [--views 30] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # run from anywhere; the tests' ROS 2 writer

from capture import pair_scene  # noqa: E402  (bench/speed/capture.py)
from mcap.reader import NonSeekingReader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from ros2_recording import write_ros2_capture  # noqa: E402

from cadio.camera.noise import NoiseConfig  # noqa: E402
from cadio.camera.render import CaptureConfig, render_views, scene_meta  # noqa: E402
from cadio.recordings.mcap_io import read_capture, write_capture  # noqa: E402


def best(repeats: int, run: Callable[[], int]) -> tuple[float, int]:
    """(best wall seconds, what ``run`` counted)."""
    times, count = [], 0
    for _ in range(repeats):
        t = time.perf_counter()
        count = run()
        times.append(time.perf_counter() - t)
    return min(times), count


def bare(path: Path) -> int:
    with path.open("rb") as fh:
        return sum(1 for _ in NonSeekingReader(fh).iter_messages(log_time_order=False))


def decode_all(path: Path, factory: Any) -> int:
    n = 0
    with path.open("rb") as fh:
        for schema, channel, message in NonSeekingReader(fh).iter_messages(log_time_order=False):
            factory.decoder_for(channel.message_encoding, schema)(message.data)
            n += 1
    return n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cfg = CaptureConfig(n_views=args.views, step_deg=360 / args.views, noise=NoiseConfig())
    parts = pair_scene()
    frames = [replace(f, timestamp_ns=1_700_000_000 * 10**9 + i * 33_333_333)
              for i, f in enumerate(render_views(parts, cfg))]
    with tempfile.TemporaryDirectory() as tmp:
        ours, ros2 = Path(tmp) / "ours.mcap", Path(tmp) / "ros2.mcap"
        write_capture(ours, frames, scene_meta(parts, cfg))
        write_ros2_capture(ros2, frames, scene=scene_meta(parts, cfg))
        n = len(frames)
        print(f"{n} views {cfg.width}x{cfg.height}; ours {ours.stat().st_size / 2**20:.1f} MiB, "
              f"ROS 2 {ros2.stat().st_size / 2**20:.1f} MiB (with a raw depth topic beside)")
        rows = [("read_capture, ours (Foxglove)", lambda: sum(1 for _ in read_capture(ours))),
                ("read_capture, ROS 2", lambda: sum(1 for _ in read_capture(ros2))),
                ("bare mcap read, ours", lambda: bare(ours)),
                ("bare mcap read, ROS 2", lambda: bare(ros2)),
                ("CDR decode, mcap_ros2", lambda: decode_all(ros2, DecoderFactory()))]
        try:
            from mcap_ros2_support_fast import DecoderFactory as FastFactory

            rows.append(("CDR decode, mcap_ros2_support_fast",
                         lambda: decode_all(ros2, FastFactory())))
        except ImportError:
            print("mcap_ros2_support_fast is not installed: its row is left out")
        print(f"{'':38s}{'seconds':>9s}{'frames/s':>10s}{'messages':>10s}")
        for name, run in rows:
            wall, count = best(args.repeats, run)
            print(f"{name:38s}{wall:9.3f}{n / wall:10.1f}{count:10d}")


if __name__ == "__main__":
    main()

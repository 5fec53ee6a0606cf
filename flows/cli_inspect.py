"""``mateqa inspect ASSEMBLY.step RECORDING.mcap``: is this assembly built as designed?

No Prefect: one recording (ROS 2 or Foxglove MCAP, as a RealSense driver writes it) checked
against the assembly's STEP (``cadio.inspect.recording``). It prints the verdict in a few lines
and writes ``as_built.csv``; exit 0 when every inspectable mate holds, 3 when one is broken, 2
on bad input (a file that cannot be read, or a recording that does not show the assembly).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_inspect_parser(sub: Any, workspace: Path) -> argparse.ArgumentParser:
    """The ``inspect`` command's parser."""
    p: argparse.ArgumentParser = sub.add_parser(
        "inspect", help="check one recording of an assembly against its design",
        description="Check a recording (ROS 2 or Foxglove MCAP: colour, depth, camera info, "
        "tf if any; no masks or part names needed) of one assembly against its STEP: the "
        "design is found in the scan, each part registered, each CAD mate read as built. "
        "Prints the verdict and writes as_built.csv (one row per face mate: index_a, "
        "index_b, face_a, face_b, relation, status, residuals). Exit 0: every inspectable "
        "mate holds; 3: a mate is broken; 2: bad input.")
    p.add_argument("step", type=Path, metavar="ASSEMBLY.step", help="the assembly's STEP file")
    p.add_argument("recording", type=Path, metavar="RECORDING.mcap", help="the recording")
    p.add_argument("--workspace", type=Path, default=workspace,
                   help=f"workspace the design is read into (default {workspace})")
    p.add_argument("--out", type=Path, default=None, metavar="CSV",
                   help="where as_built.csv goes (default: WORKSPACE/inspections/"
                   "<recording>/as_built.csv)")
    p.set_defaults(func=cmd_inspect, tol=[], tolerances_file=None)
    return p


def cmd_inspect(args: argparse.Namespace) -> int:
    from cadio.errors import InputFileError
    from cadio.inspect.recording import (
        InspectRecordingConfig,
        exit_code,
        inspect_recording,
        summary_lines,
        write_as_built,
    )
    from cadio.workspace import Workspace

    ws = Workspace(args.workspace)
    try:
        result = inspect_recording(args.step, args.recording, ws,
                                   InspectRecordingConfig(tolerances=args.tolerances))
    except InputFileError as exc:
        print(f"mateqa inspect: {exc}", file=sys.stderr)
        return 2
    out = args.out or ws.root / "inspections" / args.recording.stem / "as_built.csv"
    write_as_built(out, result)
    for line in summary_lines(result):
        print(line)
    for warning in result.warnings:
        print(f"  warning: {warning}")
    print(f"as built: {out}")
    return exit_code(result)

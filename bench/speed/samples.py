"""Benchmark: generating the built-in sample library, first time and again (nothing to do).

The first generation builds every part with build123d/bd_warehouse and writes STEP; a second
call finds the stamp and hashes unchanged and returns without writing. Both are timed here
(they used to be wall-clock assertions in the tests).

Usage: ``.venv/bin/python bench/speed/samples.py``
"""

from __future__ import annotations

import logging
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from anywhere

from cadio.samples.library import generate_library


def main() -> int:
    logging.getLogger("build123d").setLevel(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        paths = generate_library(Path(tmp))
        first = time.perf_counter() - start
        start = time.perf_counter()
        generate_library(Path(tmp))
        again = time.perf_counter() - start
    print(f"{len(paths)} files: first generation {first:.1f} s, unchanged rerun {again:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env bash
# Set up mateqa from nothing, idempotently: Debian libraries open3d needs, a virtualenv with
# every pin from constraints.txt, and the independent MCAP reader used by the tests.
# --test adds what only the tests need: Debian's chromium and its driver (the HTML report is
# opened in a headless browser).
set -euo pipefail
cd "$(dirname "$0")/.."
debs=(libusb-1.0-0 libgl1 libgomp1)
[ "${1:-}" = "--test" ] && debs+=(chromium chromium-driver)

sudo_if_needed() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

missing=()
for pkg in "${debs[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  sudo_if_needed apt-get update -qq
  sudo_if_needed env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null; then
  echo "setup: mateqa needs Python 3.11 (set PYTHON=/path/to/python3.11)" >&2
  exit 1
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# constraints.txt is the lock: every package, direct or not, at one exact version.
# torch==2.13.0 resolves to the CPU wheel; a looser pin would pull several GB of CUDA.
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[dev]"

if [ -f tests/mcap_reader/package-lock.json ] && [ ! -d tests/mcap_reader/node_modules ]; then
  echo "setup: installing the independent MCAP reader (npm @mcap/core)"
  (cd tests/mcap_reader && npm ci --silent --no-audit --no-fund)
fi
echo "setup: ready ($(.venv/bin/python --version))"

#!/usr/bin/env bash
# Set up mateqa from nothing, idempotently.
#
#   scripts/setup.sh          what a night needs (`make nightly`): the Debian libraries open3d
#                             loads and a virtualenv with the runtime pins of constraints.txt
#   scripts/setup.sh --test   what the tests need besides (`make test`): the dev extras (pytest,
#                             ruff, mypy, an MCAP checker, selenium), Debian's chromium and its
#                             driver (the HTML report is opened in a headless browser), Node with
#                             npm and the independent MCAP reader of tests/mcap_reader
#
# Debian packages are installed with apt-get: as root, or through sudo.
set -euo pipefail
cd "$(dirname "$0")/.."
test_setup=0
case "${1:-}" in
  "") ;;
  --test) test_setup=1 ;;
  *) echo "usage: scripts/setup.sh [--test]" >&2; exit 2 ;;
esac

debs=(libusb-1.0-0 libgl1 libgomp1)
if [ "$test_setup" = 1 ]; then
  debs+=(chromium chromium-driver)
  # Any Node 18 or later reads the lock of tests/mcap_reader; Debian's is taken only when none is
  # on PATH.
  command -v npm >/dev/null 2>&1 || debs+=(nodejs npm)
fi

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
# torch==2.13.0 is whatever build pip's index holds: from plain PyPI on Linux, the CUDA build.
# TORCH=cpu (the Makefile's variable) adds PyTorch's index of that build, whose 2.13.0+cpu
# pip prefers to PyPI's 2.13.0.
# pip re-resolves every pin on each call (minutes); a stamp of the lock, the package metadata
# and the chosen build skips it while none changed. The test stamp covers a night's needs too.
index=()
[ -n "${TORCH:-}" ] && index=(--extra-index-url "https://download.pytorch.org/whl/${TORCH}")
lock=$({ cat constraints.txt pyproject.toml; [ -z "${TORCH:-}" ] || echo "torch=${TORCH}"; } \
  | sha256sum | cut -d' ' -f1)
target="." stamp=.venv/.installed-run
[ "$test_setup" = 1 ] && target=".[dev]" stamp=.venv/.installed-test
# pip reads each package's index page and fetches its file one after another; so every pin of
# the lock is fetched first, eight downloads at a time, and installed from that folder alone
# (on two cores: 47 s and 27 s, where one install from the index took 138 s), and a package
# the lock does not pin fails the install instead of coming in at whatever version is newest.
# The install from the folder is uv's (the lock's own pin of it, installed first by pip): the
# same packages at the same versions as pip's install, in 27 s where pip's took 75 s.
# (The CUDA build of torch needs packages the lock, made with the CPU build, does not hold:
# where the folder alone cannot satisfy the install, pip reads the index as well.) Neither
# byte-compiles what it installs here: compileall does it on every core, skipping what is
# compiled already.
if [ "$(cat "$stamp" 2>/dev/null)" != "$lock" ] && [ "$(cat .venv/.installed-test 2>/dev/null)" != "$lock" ]; then
  fetched=$(mktemp -d)
  trap 'rm -rf "$fetched"' EXIT
  pip=(.venv/bin/python -m pip -q --disable-pip-version-check)
  { sed -n 's/^\([A-Za-z0-9_.-]*==[^ ;]*\).*/\1/p' constraints.txt; echo "setuptools>=68"; } \
    | xargs -P 8 -n 12 "${pip[@]}" download --no-deps "${index[@]}" -d "$fetched"
  # cadquery-ocp and cadquery-ocp-novtk (build123d's) both write OCP's kernel module, with and
  # without VTK; cadquery needs the one with VTK, so cadquery-ocp writes it again last.
  uv=(.venv/bin/uv pip install -q --no-cache --python .venv/bin/python --no-index
      --find-links "$fetched" -c constraints.txt)
  if ! { "${pip[@]}" install --no-compile --no-index --find-links "$fetched" -c constraints.txt uv \
         && "${uv[@]}" -e "$target" \
         && "${uv[@]}" --reinstall-package cadquery-ocp cadquery-ocp; } 2>/dev/null; then
    echo "setup: the lock's packages alone do not install here; reading the index as well"
    "${pip[@]}" install --no-compile --find-links "$fetched" "${index[@]}" \
      -c constraints.txt -e "$target"
  fi
  # (a package may ship a file no Python 3.11 compiles, as pip's own compile skips it; the
  # packages' own test suites, which nothing here imports, are a fifth of the files: 39 s
  # without them where all took 55 s; nor does anything import sympy (torch only for its
  # compiler), pip, or plotly's 1,400 classes of figure parts (open3d imports its figure))
  .venv/bin/python -m compileall -q -j 0 -x '/tests?/|/site-packages/(sympy|pip)/|/plotly/graph_objs/[a-z]' \
    .venv/lib/python3.11/site-packages >/dev/null || true
  echo "$lock" > "$stamp"
fi

if [ "$test_setup" = 1 ] && [ ! -d tests/mcap_reader/node_modules ]; then
  echo "setup: installing the independent MCAP reader (npm @mcap/core)"
  (cd tests/mcap_reader && npm ci --silent --no-audit --no-fund)
fi
# The project's own modules byte-compiled now (a fraction of a second; only what changed): a
# night and the tests start many processes that import them, and where PYTHONDONTWRITEBYTECODE
# is set none of them would keep what it compiled.
.venv/bin/python -m compileall -q -j 0 cadio models flows reports tests bench >/dev/null || true
echo "setup: ready ($(.venv/bin/python --version))"

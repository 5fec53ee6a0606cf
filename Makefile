# The README's commands. `make nightly`: set up what a night needs, then run one on the built-in
# sample library. `make test`: set up what the tests need besides, then ruff, mypy and the test
# suite (exactly what CI runs, .ci/run).
.PHONY: setup setup-test nightly serve stop-server test lint bench

WORKSPACE ?= workspace
# The PyTorch build the set-up installs (torch==2.13.0, the lock's pin). Empty: whatever pip's
# index gives, which from plain PyPI on Linux is the CUDA build with NVIDIA's CUDA libraries.
# TORCH=cpu (or another build of PyTorch's wheel index, e.g. cu126) adds that index,
# https://download.pytorch.org/whl/$(TORCH), so `make nightly TORCH=cpu` installs the CPU build.
# Choose it before the first set-up: an installed torch of the pinned version is kept.
TORCH ?=
export TORCH

setup:
	@bash scripts/setup.sh

setup-test:
	@bash scripts/setup.sh --test

nightly: setup
	.venv/bin/mateqa nightly --workspace $(WORKSPACE)

# A local Prefect server with its UI on :4200 (it takes over the one a night left running), a
# process work pool and worker, the deployments of prefect.yaml; then
# `prefect deployment run 'nightly/nightly' --watch`. Ctrl-C stops it all.
serve: setup
	.venv/bin/mateqa serve

# Stop the Prefect server a night left running on :4200.
stop-server:
	.venv/bin/mateqa serve --stop

lint: setup-test
	.venv/bin/ruff check .
	.venv/bin/mypy

# ruff, then mypy beside the test suite: a cold mypy is a minute of one core, and the suite
# leaves about a fifth of two cores idle while it waits on servers and nights. mypy's report
# is printed after the tests'; either failing fails the target.
test: setup-test
	.venv/bin/ruff check .
	@types=$$(mktemp); .venv/bin/mypy > "$$types" 2>&1 & mypy=$$!; \
	.venv/bin/python -m pytest; tests=$$?; \
	wait $$mypy; typed=$$?; echo "mypy:"; cat "$$types"; rm -f "$$types"; \
	test $$tests -eq 0 && test $$typed -eq 0

bench: setup
	.venv/bin/python bench/speed/ingest.py
	.venv/bin/python bench/speed/nightly.py

# The two commands of the README: `make nightly` (set up + run the main job) and `make test`.
.PHONY: setup nightly test lint bench

WORKSPACE ?= workspace

setup:
	@bash scripts/setup.sh

nightly: setup
	.venv/bin/mateqa nightly --workspace $(WORKSPACE)

lint: setup
	.venv/bin/ruff check .
	.venv/bin/mypy

test: lint
	.venv/bin/python -m pytest

bench: setup
	.venv/bin/python bench/ingest.py

# The two commands of the README: `make nightly` (set up + run the main job) and `make test`.
.PHONY: setup setup-test nightly serve test lint bench

WORKSPACE ?= workspace

setup:
	@bash scripts/setup.sh

setup-test:
	@bash scripts/setup.sh --test

nightly: setup
	.venv/bin/mateqa nightly --workspace $(WORKSPACE)

# A local Prefect server (UI on :4200), a process work pool and worker, the deployments of
# prefect.yaml; then `prefect deployment run 'nightly/nightly' --watch`. Ctrl-C stops it.
serve: setup
	.venv/bin/mateqa serve

lint: setup-test
	.venv/bin/ruff check .
	.venv/bin/mypy

test: lint
	.venv/bin/python -m pytest

bench: setup
	.venv/bin/python bench/ingest.py
	.venv/bin/python bench/nightly.py

# The README's commands. `make nightly`: set up what a night needs, then run one on the built-in
# sample library. `make test`: set up what the tests need besides, then ruff, mypy and the test
# suite (exactly what CI runs, .ci/run).
.PHONY: setup setup-test nightly serve stop-server test lint bench

WORKSPACE ?= workspace

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

test: lint
	.venv/bin/python -m pytest

bench: setup
	.venv/bin/python bench/ingest.py
	.venv/bin/python bench/nightly.py

"""The logger of the flow or task run this code runs in, or a module's where there is none.

Stage code of ``flows/`` runs inside a flow run (its lines belong in the run's log, which the
UI shows) but also outside one: in a signal handler, or called directly by ``bench/nightly.py``.
"""

from __future__ import annotations

import logging
from typing import Any


def run_logger(fallback: str) -> Any:
    """Prefect's run logger, or the logger named ``fallback`` outside a run context."""
    from prefect import get_run_logger

    try:
        return get_run_logger()
    except Exception:  # no run context in this thread: the module's logger will do
        return logging.getLogger(fallback)

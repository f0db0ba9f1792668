"""Shared fixtures: the golden traces and a helper that runs any env through a jitted episode."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from snac_jax.replay import GOLDEN_TRACES_ENV_VAR, load_traces

BUNDLED_TRACES = Path(__file__).parent / "data" / "golden_traces.json.gz"


def golden_traces_path() -> Path:
    """`$SNAC_GOLDEN_TRACES` when set, else the copy of the reference traces in tests/data."""
    return Path(os.environ.get(GOLDEN_TRACES_ENV_VAR) or BUNDLED_TRACES)


_TRACES = load_traces(golden_traces_path())


@pytest.fixture(params=range(len(_TRACES)), ids=[f"{t['variant']}-{i}" for i, t in enumerate(_TRACES)])
def golden_trace(request):
    return _TRACES[request.param]

"""Shared fixtures: the golden traces and a helper that runs any env through a jitted episode.

Also a compilation cache for the test run: many tests compile the same XLA programs (the same env
step, agents and tiny networks under fresh closures, in both xdist workers and in the CLI and
notebook subprocesses, which inherit the environment variables). Caching every program on disk
compiles each once; on a cold cache it cut tests/test_dqn.py, test_train_driver.py and
test_ppo.py from 358 s to 293 s on 2 cores. A cache hit still traces and lowers, so the
compile-once tests, which count traces and jit cache entries, are unaffected. Set
`JAX_COMPILATION_CACHE_DIR` to use another directory; a whole test run leaves about 100 MB there.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(tempfile.gettempdir()) / "snac-jax-tests-xla-cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# No eviction (-1): jax's eviction reads every entry's access-time file, and a test that kills a
# training process mid-write can leave an entry without one, after which every cache write warns.
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", "-1")
# Computations run inline, not dispatched asynchronously: with async dispatch the CPU client can
# hang for good on a host callback inside a jitted loop (jax-ml/jax#25861, open), and the tests'
# spies (`jax.debug.callback`) and JaxMARL's IPPO script (`io_callback`) do that. The package
# itself makes no callbacks, so its users' programs are not exposed.
os.environ.setdefault("JAX_CPU_ENABLE_ASYNC_DISPATCH", "false")

import jax  # noqa: E402  (after the variables above, which jax reads when it is imported)
import pytest  # noqa: E402

for _name, _value in (
    ("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"]),
    ("jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])),
    ("jax_compilation_cache_max_size", int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"])),
    ("jax_cpu_enable_async_dispatch", os.environ["JAX_CPU_ENABLE_ASYNC_DISPATCH"].lower() in ("1", "true")),
):
    jax.config.update(_name, _value)  # in case a plugin imported jax before this module

from snac_jax.replay import GOLDEN_TRACES_ENV_VAR, load_traces  # noqa: E402

BUNDLED_TRACES = Path(__file__).parent / "data" / "golden_traces.json.gz"


def golden_traces_path() -> Path:
    """`$SNAC_GOLDEN_TRACES` when set, else the copy of the reference traces in tests/data."""
    return Path(os.environ.get(GOLDEN_TRACES_ENV_VAR) or BUNDLED_TRACES)


try:
    _TRACES, _TRACES_ERROR = load_traces(golden_traces_path()), None
except ValueError as error:  # an empty or cut file: every test that reads traces fails with this
    _TRACES, _TRACES_ERROR = [], str(error)


def golden_traces() -> list[dict]:
    """Every golden trace; fails the calling test when the file is empty, cut or unreadable."""
    if _TRACES_ERROR is not None:
        pytest.fail(f"golden traces: {_TRACES_ERROR}")
    return _TRACES


def _trace_params(select=lambda trace: True):
    """Parameters of a fixture over the traces `select` accepts (one failing case when the
    file does not load, so a bad `SNAC_GOLDEN_TRACES` fails instead of leaving nothing to run)."""
    if _TRACES_ERROR is not None:
        return [pytest.param(None, id="unreadable-golden-traces")]
    return [pytest.param(i, id=f"{t['variant']}-{i}") for i, t in enumerate(_TRACES) if select(t)]


@pytest.fixture(params=_trace_params())
def golden_trace(request):
    return golden_traces()[request.param]


@pytest.fixture(params=_trace_params(lambda trace: "dynamic" in trace["variant"]))
def dynamic_golden_trace(request):
    """The traces of dynamic tasks (their observations append the design)."""
    return golden_traces()[request.param]

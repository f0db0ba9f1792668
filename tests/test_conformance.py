"""Exact conformance with the reference implementation (SPEC §10).

Every recorded episode is replayed with its actions and recorded strides; every observation,
reward, done flag, the final grid and the final IoU must be equal. Set `SNAC_GOLDEN_TRACES` to
check any trace file in the same format.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from snac_jax import grid_iou
from snac_jax.replay import GOLDEN_TRACES_ENV_VAR, env_for_trace, load_traces, replay
from tests.conftest import BUNDLED_TRACES

ROOT = Path(__file__).resolve().parent.parent


def test_replay_matches_golden_trace(golden_trace):
    trace = golden_trace
    env, params = env_for_trace(trace)
    out = replay(env, params, trace["actions"], trace["strides"])

    expected_obs = np.asarray(trace["observations"], dtype=np.float32)
    # The traces record window + N_b + N_s; dynamic tasks append the design after them.
    got_obs = out["observations"][:, : expected_obs.shape[1]]
    assert got_obs.shape == expected_obs.shape
    mismatch = np.flatnonzero(np.any(got_obs != expected_obs, axis=1))
    assert mismatch.size == 0, f"first observation mismatch at t={mismatch[:1]}"
    np.testing.assert_array_equal(out["rewards"], np.asarray(trace["rewards"], dtype=np.float32))
    np.testing.assert_array_equal(out["terminated"] | out["truncated"], np.asarray(trace["dones"]))
    np.testing.assert_array_equal(out["final_grid"], np.asarray(trace["final_grid"]))
    assert out["final_iou"] == np.float32(trace["final_iou"])
    # The IoU the env keeps incrementally equals the one computed from the cells.
    assert abs(grid_iou(out["final_grid"], trace["design"], int(trace["dim"])) - trace["final_iou"]) < 1e-12


def test_dynamic_observation_appends_the_design(dynamic_golden_trace):
    trace = dynamic_golden_trace
    env, params = env_for_trace(trace)
    assert env.config.dynamic
    out = replay(env, params, trace["actions"][:3], trace["strides"][:3])
    design_part = out["observations"][:, len(trace["observations"][0]) :]
    expected = np.asarray(trace["design"], dtype=np.float32).reshape(-1)
    for row in design_part:
        np.testing.assert_array_equal(row, expected)


def _cut_copy(tmp_path):
    """The bundled traces cut in half: a gzip stream that ends early."""
    data = BUNDLED_TRACES.read_bytes()
    path = tmp_path / "cut.json.gz"
    path.write_bytes(data[: len(data) // 2])
    return path


@pytest.mark.parametrize(
    "content, message",
    [
        ("[]", "non-empty JSON list"),
        ("", "not a readable golden-trace file"),
        ('{"variant": "1d-static-sin"}', "non-empty JSON list"),
        ('[{"variant": "1d-static-sin"}]', "trace 0 is incomplete: lacks"),
    ],
)
def test_an_empty_or_incomplete_trace_file_is_refused(tmp_path, content, message):
    path = tmp_path / "traces.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        load_traces(path)


def test_a_cut_trace_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="cut.json.gz: not a readable golden-trace file"):
        load_traces(_cut_copy(tmp_path))
    trace = load_traces(BUNDLED_TRACES)[0]
    (tmp_path / "short.json").write_text(json.dumps([{**trace, "rewards": trace["rewards"][:-1]}]))
    with pytest.raises(ValueError, match="disagree in length"):
        load_traces(tmp_path / "short.json")


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_bad_SNAC_GOLDEN_TRACES_fails_the_conformance_tests(tmp_path):
    """Pointed at an empty file, the conformance and NumPy-engine tests fail (they used to be
    skipped, or to pass over zero traces); a cut file fails the same way (`load_traces` above)."""
    (tmp_path / "empty.json").write_text("[]")
    for bad in (tmp_path / "empty.json",):
        env = {**os.environ, GOLDEN_TRACES_ENV_VAR: str(bad), "JAX_PLATFORMS": "cpu"}
        tests = [
            "tests/test_conformance.py::test_replay_matches_golden_trace",
            "tests/test_conformance.py::test_dynamic_observation_appends_the_design",
            "tests/test_numpy_engine.py::test_numpy_engine_replays_every_golden_trace",
        ]
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-n", "0", "-p", "no:cacheprovider", "-q", *tests],
            capture_output=True,
            text=True,
            env=env,
            cwd=ROOT,
            timeout=300,
        )
        summary = done.stdout.strip().splitlines()[-1]
        # the two fixture-driven tests error in their fixture, the NumPy-engine one fails
        assert done.returncode == 1 and "1 failed, 2 errors" in summary, done.stdout[-2000:]
        assert "passed" not in summary and "skipped" not in summary
        # one traceback line per test (the short summary repeats it only where the terminal is wide)
        assert done.stdout.count("E           Failed: golden traces: ") == 3, done.stdout[-2000:]

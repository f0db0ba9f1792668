"""Exact conformance with the reference implementation (SPEC §10).

Every recorded episode is replayed with its actions and recorded strides; every observation,
reward, done flag, the final grid and the final IoU must be equal. Set `SNAC_GOLDEN_TRACES` to
check any trace file in the same format.
"""

import numpy as np

from snac_jax import grid_iou
from snac_jax.replay import env_for_trace, replay


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


def test_dynamic_observation_appends_the_design(golden_trace):
    trace = golden_trace
    env, params = env_for_trace(trace)
    if not env.config.dynamic:
        return
    out = replay(env, params, trace["actions"][:3], trace["strides"][:3])
    design_part = out["observations"][:, len(trace["observations"][0]) :]
    expected = np.asarray(trace["design"], dtype=np.float32).reshape(-1)
    for row in design_part:
        np.testing.assert_array_equal(row, expected)

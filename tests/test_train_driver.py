"""The shared training driver: run directory contents, checkpoint round trip, resume equal to an
uninterrupted run, a 2-device run, the CLI and the checkpoint policy loader."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents import checkpoint, trained
from agents.registry import make_config
from agents.driver import chunk_sizes, initial_state, read_metrics, train

TINY = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8)


def _leaves_equal(a, b) -> bool:
    a, b = checkpoint.to_storable(a), checkpoint.to_storable(b)
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_chunk_sizes_cover_the_run():
    assert chunk_sizes(10, 3) == [4, 4, 2]
    assert chunk_sizes(9, 3) == [3, 3, 3]
    assert chunk_sizes(2, 20) == [1, 1]


def test_checkpoint_round_trip(tmp_path):
    config = make_config("ppo", "1d-static-sin", recurrent=True, seeds=2, total_steps=128, **TINY)
    from agents.registry import build_algorithm

    algorithm = build_algorithm(config)
    state = initial_state(algorithm)
    checkpoint.save_state(tmp_path, 0, state)
    assert checkpoint.latest_chunk(tmp_path) == 0
    chunk, restored = checkpoint.restore_state(tmp_path, initial_state(algorithm))
    assert chunk == 0 and _leaves_equal(state, restored)
    assert jax.dtypes.issubdtype(restored.key.dtype, jax.dtypes.prng_key)


def test_resume_equals_uninterrupted(tmp_path):
    config = make_config("ppo", "1d-static-gauss", recurrent=True, seeds=2, total_steps=4 * 16 * 8, chunks=4, **TINY)
    _, straight = train(config, tmp_path / "straight", progress=False)
    _, first = train(config, tmp_path / "killed", progress=False, stop_after_chunks=2)
    assert int(first.update[0]) == 2
    # A crash after the metrics line but before the checkpoint: resume drops the extra line.
    with (tmp_path / "killed" / checkpoint.METRICS_FILE).open("a") as f:
        f.write(json.dumps({"chunk": 2, "wall_s": 0.0}) + "\n")
    _, resumed = train(config, tmp_path / "killed", resume=True, progress=False)
    assert int(resumed.update[0]) == 4
    assert _leaves_equal(straight, resumed)
    straight_lines, resumed_lines = read_metrics(tmp_path / "straight"), read_metrics(tmp_path / "killed")
    assert [r["chunk"] for r in resumed_lines] == [0, 1, 2, 3]
    assert [r["iou"] for r in resumed_lines] == [r["iou"] for r in straight_lines]


def test_new_run_refuses_an_existing_run_and_resume_needs_one(tmp_path):
    config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
    train(config, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="already holds a run"):
        train(config, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="config.json is missing"):
        train(config, tmp_path / "empty", resume=True, progress=False)


def test_checkpoint_that_does_not_match_its_config_is_a_clear_error(tmp_path):
    config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
    train(config, tmp_path, progress=False)
    saved = json.loads((tmp_path / checkpoint.CONFIG_FILE).read_text())
    saved["hidden_size"] = 2 * saved["hidden_size"]
    (tmp_path / checkpoint.CONFIG_FILE).write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=r"does not hold the state its config.json describes .*the config needs"):
        trained.load_trained(tmp_path)


TWO_DEVICES = textwrap.dedent(
    """
    import json, sys
    import jax
    from agents.registry import make_config
    from agents.driver import train
    from snac_jax.evaluation import run_episodes
    from snac_jax.devices import env_mesh
    import numpy as np

    devices = int(sys.argv[1])
    config = make_config("ppo", "1d-static-step", recurrent=False, update_epochs=4, num_minibatches=4, reward_scale=0.1, ent_coef_end=0.01, total_steps=200_000, num_envs=64, rollout_steps=40,
                         hidden_size=32, learning_rate=3e-3, max_steps=40, chunks=2)
    mesh = env_mesh(devices)
    algorithm, state = train(config, sys.argv[2], progress=False, mesh=mesh)
    before = algorithm.init(jax.random.key(0)).params
    def iou(params):
        out = run_episodes(algorithm.env, algorithm.env_params, algorithm.policy(params), jax.random.key(5), np.zeros(64, np.int32))
        return float(np.mean(out.iou))
    shardings = {tuple(x.sharding.spec) for x in jax.tree.leaves(state.worlds)}
    print(json.dumps({
        "devices": len(jax.devices()),
        "shapes": [list(x.shape) for x in jax.tree.leaves(state)],
        "world_specs": [list(s) for s in shardings],
        "iou_before": iou(before),
        "iou_after": iou(jax.tree.map(lambda x: x[0], state.params)),
    }))
    """
)


def _run_devices(devices: int, out_dir) -> dict:
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}", "JAX_PLATFORMS": "cpu"}
    result = subprocess.run([sys.executable, "-c", TWO_DEVICES, str(devices), str(out_dir)],
                            capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # two training subprocesses: ~1 min idle, minutes on a loaded 2-core CPU
def test_two_device_run_matches_one_device_shapes_and_learns(tmp_path):
    two = _run_devices(2, tmp_path / "two")
    one = _run_devices(1, tmp_path / "one")
    assert two["devices"] == 2 and one["devices"] == 1
    assert two["shapes"] == one["shapes"]
    assert two["world_specs"] == [[None, "envs"]]
    # The bar of tests/test_ppo.py's short-episode run: 85% of the best IoU 40 steps allow.
    assert two["iou_after"] > 0.85 * 40 / 600 and two["iou_after"] > two["iou_before"], two


def test_cli_train_writes_the_run_directory_and_eval_loads_it(tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "snac_jax.cli", "train", "ppo", "--task", "1d-static-sin", "--recurrent",
           "--total-steps", "256", "--num-envs", "16", "--chunks", "2", "--out", str(out), "--eval-episodes", "4",
           "--no-progress"]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    assert "| 1d-static-sin |" in result.stdout
    assert "worlds split over 1 cpu device(s)" in result.stderr  # training's CPU default
    evaluation = json.loads((out / "eval.json").read_text())
    assert 0.0 <= evaluation["1d-static-sin"]["mean"] <= 1.0

    from snac_jax.evaluation import evaluate_task

    again = evaluate_task("1d-static-sin", lambda env: trained.checkpoint_policy(env, out), static_episodes=4)
    assert again.mean == pytest.approx(evaluation["1d-static-sin"]["mean"])


def test_checkpoint_policy_rejects_another_task(tmp_path):
    config = make_config("ppo", "1d-static-sin", total_steps=128, chunks=1, **TINY)
    train(config, tmp_path, progress=False)
    from snac_jax.tasks import make

    env, _ = make("1d-static-step")
    with pytest.raises(ValueError, match="trained on '1d-static-sin'"):
        trained.checkpoint_policy(env, tmp_path)


def test_a_checkpoint_with_empty_slots_restores_into_a_state_without_them(tmp_path):
    """A state saved when a field held None (as the DQN's hindsight fields did before hindsight
    got its own module) restores into the same state without that field."""
    from flax import struct

    @struct.dataclass
    class Before:
        weights: jax.Array
        extra: Any = None

    @struct.dataclass
    class After:
        weights: jax.Array

    checkpoint.save_state(tmp_path, 0, Before(weights=jnp.arange(6.0).reshape(2, 3)))
    chunk, restored = checkpoint.restore_state(tmp_path, After(weights=jnp.zeros((2, 3))))
    assert chunk == 0 and isinstance(restored, After)
    np.testing.assert_array_equal(restored.weights, np.arange(6.0).reshape(2, 3))


def test_a_checkpoint_of_another_shape_is_refused_before_reading(tmp_path):
    checkpoint.save_state(tmp_path, 3, {"w": jnp.zeros((2, 3)), "b": jnp.zeros(3)})
    with pytest.raises(ValueError, match=r"checkpoint 3 does not hold the state .*w is float32\[2, 3\], the config needs float32\[4, 3\]"):
        checkpoint.restore_state(tmp_path, {"w": jnp.zeros((4, 3)), "b": jnp.zeros(3)})
    with pytest.raises(ValueError, match="missing c; unexpected b"):
        checkpoint.restore_state(tmp_path, {"w": jnp.zeros((2, 3)), "c": jnp.zeros(3)})

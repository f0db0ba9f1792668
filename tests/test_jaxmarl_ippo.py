"""JaxMARL's own IPPO baseline (`baselines/IPPO/ippo_ff_mpe.py`) trains on `snac_jax.multi` with
only its environment line changed: the script is vendored under tests/fixtures/jaxmarl/ and run
for a few updates as its `main` runs it (`vmap` over seeds of a jitted `train`). It asks for the
spaces inside `jit`, steps a vmapped `env.step` with per-agent actions of shape `(1,)`, and wraps
the env in JaxMARL's `LogWrapper` with `replace_info=True`. Skipped unless `jaxmarl` (the
`[jaxmarl]` extra) is installed."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import jax
import numpy as np
import pytest

pytest.importorskip("jaxmarl")
pytest.importorskip("distrax")
pytest.importorskip("optax")

SCRIPT = Path(__file__).parent / "fixtures" / "jaxmarl" / "ippo_ff_mpe.py"
NUM_ENVS, NUM_STEPS, NUM_UPDATES, NUM_SEEDS, MAX_STEPS = 4, 16, 3, 2, 6


def _load_script(monkeypatch, logged: list[dict]):
    """The vendored script as a module. Its `main` (not run here) uses hydra, omegaconf and wandb;
    the training loop logs each update's metrics through `wandb.log`, which the stand-in records."""
    wandb = types.ModuleType("wandb")
    wandb.log = lambda metric: logged.append(jax.tree.map(np.asarray, metric))
    hydra = types.ModuleType("hydra")
    hydra.main = lambda **kwargs: lambda function: function
    omegaconf = types.ModuleType("omegaconf")
    omegaconf.OmegaConf = types.SimpleNamespace(to_container=dict)
    for name, module in (("wandb", wandb), ("hydra", hydra), ("omegaconf", omegaconf)):
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("jaxmarl_ippo_ff_mpe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # flax looks its modules' classes up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_jaxmarls_ippo_script_trains_on_a_two_robot_team(monkeypatch):
    logged: list[dict] = []
    script = _load_script(monkeypatch, logged)
    config = {  # the script's own config (config/ippo_ff_mpe.yaml) at a tiny budget
        "LR": 2.5e-4,
        "NUM_ENVS": NUM_ENVS,
        "NUM_STEPS": NUM_STEPS,
        "TOTAL_TIMESTEPS": NUM_ENVS * NUM_STEPS * NUM_UPDATES,
        "UPDATE_EPOCHS": 2,
        "NUM_MINIBATCHES": 2,
        "GAMMA": 0.99,
        "GAE_LAMBDA": 0.95,
        "CLIP_EPS": 0.2,
        "ENT_COEF": 0.01,
        "VF_COEF": 0.5,
        "MAX_GRAD_NORM": 0.5,
        "ACTIVATION": "tanh",
        "ENV_NAME": "2d-static-dense",
        "ENV_KWARGS": {"num_robots": 2, "max_steps": MAX_STEPS},
        "ANNEAL_LR": True,
    }
    train = jax.jit(script.make_train(config))
    out = jax.vmap(train)(jax.random.split(jax.random.key(30), NUM_SEEDS))  # as the script's main

    metrics = jax.tree.map(np.asarray, out["metrics"])
    assert metrics["returned_episode_returns"].shape == (NUM_SEEDS, NUM_UPDATES)
    assert all(np.isfinite(v).all() for v in metrics.values())
    # Every episode is truncated at MAX_STEPS: the wrapper saw whole episodes end.
    assert metrics["returned_episode"].min() > 0
    np.testing.assert_allclose(metrics["returned_episode_lengths"][:, 1:], MAX_STEPS)
    # The team shares one reward (SPEC §13): both robots' logged returns are equal.
    state = out["runner_state"][1]
    returns = np.asarray(state.returned_episode_returns)
    np.testing.assert_array_equal(returns[..., 0], returns[..., 1])
    assert len(logged) == NUM_SEEDS * NUM_UPDATES and all(np.isfinite(m["total_loss"]) for m in logged)

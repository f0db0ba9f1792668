"""PQN / PQN-RNN: Q(lambda) returns by hand, the learner's targets and loss by hand, the truncation
values, the LayerNorm GRU Q-network against step-by-step application, the rollout's Q-values against
a pass over the sequence, tiny training runs, one compile per configuration, seeds, resume, the CLI,
and the paper's missing row.

Episodes are cut short with the `max_steps` training option so that short rollouts hold both
terminations and truncations.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.inputs import ObsLayout
from agents.common.networks import ActorCritic, LayerNormQNetwork
from agents.common.targets import q_lambda, truncation_values
from agents.learners.pqn import PQN, Transition
from agents.training.registry import make_config
from snac_jax.evaluation import run_episodes
from snac_jax.tasks import make
from tests.helpers import check_each_seed_evaluates_from_the_checkpoint

# Every option a tuned per-task entry may set is pinned here, so retuning never changes the tests.
TINY = dict(
    recurrent=False,
    num_envs=8,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=2,
    hidden_size=16,
    rnn_size=8,
    learning_rate=1e-3,
    reward_scale=0.01,
    chunks=2,
    total_steps=2 * 8 * 8,
    stagger_starts=False,
    time_limit_ends=False,
)


def _pqn(task="1d-static-sin", **options) -> PQN:
    return PQN(make_config("pqn", task, **{**TINY, **options}))


# Two agents shared by the tests below, so that each compiles its programs (init, rollout,
# training chunk) once for the file: episodes cut at 6 steps, so that 8-step rollouts hold
# terminations and truncations.


@pytest.fixture(scope="module")
def static_feed_forward():
    """`(agent, its initial state)`: feed-forward, on 1d-static-sin."""
    pqn = _pqn("1d-static-sin", recurrent=False, max_steps=6)
    return pqn, jax.jit(pqn.init)(jax.random.key(0))


@pytest.fixture(scope="module")
def dynamic_recurrent():
    """`(agent, its initial state)`: recurrent, on 1d-dynamic."""
    pqn = _pqn("1d-dynamic", recurrent=True, max_steps=6)
    return pqn, jax.jit(pqn.init)(jax.random.key(0))


# --- pure pieces -------------------------------------------------------------------------------------


def test_q_lambda_matches_hand_computation_with_a_termination_and_a_truncation():
    gamma = 0.9
    # One world, 5 steps. Step 1 terminates (its reward alone), step 3 is truncated (bootstraps
    # from its final observation's value 7 and cuts the trace). The next values at steps 1 and 3
    # are the next episode's first observation (20, 40) and must be ignored, as must the final
    # values where no truncation happened (99).
    rewards = jnp.array([1.0, 2.0, 3.0, 4.0, 5.0])[:, None]
    next_values = jnp.array([10.0, 20.0, 30.0, 40.0, 50.0])[:, None]
    final_values = jnp.array([99.0, 99.0, 99.0, 7.0, 99.0])[:, None]
    terminated = jnp.array([False, True, False, False, False])[:, None]
    truncated = jnp.array([False, False, False, True, False])[:, None]

    got = q_lambda(rewards, next_values, final_values, terminated, truncated, gamma, 0.5)
    # lambda = 0.5:
    # G4 = 5 + 0.9 * 50                          = 50.0   (the rollout's end: bootstrap from V(s5))
    # G3 = 4 + 0.9 * 7                           = 10.3   (truncated: the final observation's value)
    # G2 = 3 + 0.9 * (0.5 * 30 + 0.5 * 10.3)     = 3 + 0.9 * 20.15 = 21.135
    # G1 = 2                                     = 2.0    (terminated: nothing beyond)
    # G0 = 1 + 0.9 * (0.5 * 10 + 0.5 * 2)        = 1 + 0.9 * 6 = 6.4
    np.testing.assert_allclose(got[:, 0], [6.4, 2.0, 21.135, 10.3, 50.0], rtol=1e-6)

    # lambda = 1 (Monte-Carlo up to the episode's end): G2 = 3 + 0.9 * 10.3 = 12.27, G0 = 1 + 0.9 * 2 = 2.8.
    got = q_lambda(rewards, next_values, final_values, terminated, truncated, gamma, 1.0)
    np.testing.assert_allclose(got[:, 0], [2.8, 2.0, 12.27, 10.3, 50.0], rtol=1e-6)
    # lambda = 0 (one-step Q-learning): G0 = 1 + 9, G2 = 3 + 27, the ends as above.
    got = q_lambda(rewards, next_values, final_values, terminated, truncated, gamma, 0.0)
    np.testing.assert_allclose(got[:, 0], [10.0, 2.0, 30.0, 10.3, 50.0], rtol=1e-6)
    # Terminated and truncated on the same step: a termination, nothing bootstrapped.
    both = q_lambda(rewards, next_values, final_values, terminated | truncated, truncated, gamma, 0.5)
    assert float(both[3, 0]) == pytest.approx(4.0)


def _pqn_whose_q_values_are_its_input(**options) -> PQN:
    pqn = _pqn(gamma=0.5, q_lambda=0.25, reward_scale=2.0, **options)

    def network(params, carry, obs, resets, mutable=None):
        out = (carry, obs)  # Q-values (T, B, A) = the input
        return (out, {}) if mutable else out

    pqn.network = SimpleNamespace(apply=network)
    pqn._network_obs = lambda worlds: worlds.obs
    return pqn


def _hand_rollout() -> tuple[Transition, SimpleNamespace]:
    """Four steps of one world: a truncation at row 1, a step both terminated and truncated at row 2."""
    q = lambda *rows: jnp.array(rows, jnp.float32)[:, None]  # (T, B=1, A=2)
    batch = Transition(
        obs=q([7, 0], [0, 6], [1, 3], [0, 10]),  # the Q-values the loss learns (the parameters moved since)
        reset=jnp.zeros((4, 1), bool),
        action=jnp.array([0, 1, 0, 1])[:, None],
        value=jnp.array([10.0, 20.0, 30.0, 40.0])[:, None],  # max Q as the rollout computed it
        reward=jnp.array([1.0, 2.0, 3.0, 4.0])[:, None],  # learned from as 2, 4, 6, 8 (reward_scale 2)
        terminated=jnp.array([False, False, True, False])[:, None],
        truncated=jnp.array([False, True, True, False])[:, None],
        final_obs=q([99, 99], [4, 5], [100, 100], [99, 99]),
        carry_after=jnp.zeros((4, 1, 1)),
    )
    stopped = SimpleNamespace(obs=jnp.array([[7.0, 8.0]]), carry=jnp.zeros((1, 1)), reset=jnp.zeros((1,), bool))
    return batch, stopped


def _targets_and_loss(pqn):
    """`PQN.targets` and `PQN._loss` of the hand rollout, jitted as one program (op by op, some eighty)."""
    batch, stopped = _hand_rollout()

    @jax.jit
    def run():
        targets = pqn.targets(None, batch, stopped)
        return targets, pqn._loss(None, None, batch, targets)

    return run()


def test_learner_targets_and_loss_match_hand_computation():
    """`PQN.targets` and `PQN._loss` with the network replaced by one whose Q-values are its input:
    the next values are the rollout's own shifted one row (the last from where the rollout
    stopped), a truncation bootstraps from its final observation, a step both terminated and
    truncated bootstraps nothing."""
    pqn = _pqn_whose_q_values_are_its_input()
    targets, (loss, info) = _targets_and_loss(pqn)
    # G3 = 8 + 0.5 * 8 = 12 (the rollout's end: max Q where it stopped)
    # G2 = 6 (terminated, and truncated: its final observation's 100 is not read)
    # G1 = 4 + 0.5 * 5 = 6.5 (truncated: max Q of its final observation, not of the row's own 6)
    # G0 = 2 + 0.5 * (0.75 * 20 + 0.25 * 6.5) = 10.3125 (the next value is row 1's, 20)
    np.testing.assert_allclose(targets[:, 0], [10.3125, 6.5, 6.0, 12.0], rtol=1e-6)
    # Taken Q-values 7, 6, 1, 10: errors -3.3125, -0.5, -5, -2; squares 10.97265625, 0.25, 25, 4;
    # half their mean: 0.5 * 40.22265625 / 4
    np.testing.assert_allclose(loss, 0.5 * 40.22265625 / 4, rtol=1e-6)
    np.testing.assert_allclose(info["q_mean"], 6.0, rtol=1e-6)


def test_with_time_limit_ends_a_truncation_ends_the_return_as_a_termination_does():
    """The rollout above with `time_limit_ends`: row 1's truncation no longer reads its final
    observation's values, and row 0's trace stops there."""
    pqn = _pqn_whose_q_values_are_its_input(time_limit_ends=True)
    targets, (loss, _) = _targets_and_loss(pqn)
    # G3 = 12 and G2 = 6 as above; G1 = 4 (ended: the final observation's 5 is not read)
    # G0 = 2 + 0.5 * (0.75 * 20 + 0.25 * 4) = 10.0
    np.testing.assert_allclose(targets[:, 0], [10.0, 4.0, 6.0, 12.0], rtol=1e-6)
    # Taken Q-values 7, 6, 1, 10: errors -3, 2, -5, -2; squares 9, 4, 25, 4; half their mean: 0.5 * 42 / 4
    np.testing.assert_allclose(loss, 5.25, rtol=1e-6)


@pytest.mark.parametrize("truncations", [3, 7])  # fewer than the 4 worlds, more (two a world at most)
def test_truncation_values_score_exactly_the_truncated_steps(truncations):
    t, n = 5, 4
    rng = np.random.default_rng(truncations)
    truncated = np.zeros(t * n, bool)
    truncated[rng.choice(t * n, size=truncations, replace=False)] = True
    final_obs = rng.normal(size=(t, n, 3)).astype(np.float32)
    carry = rng.normal(size=(t, n, 2)).astype(np.float32)

    def score(c, o):
        return o.sum(-1) * c[:, 0]

    values = jax.jit(truncation_values, static_argnums=(0, 4))
    got = values(score, jnp.asarray(truncated.reshape(t, n)), final_obs, carry, 2)
    expected = np.where(truncated.reshape(t, n), final_obs.sum(-1) * carry[..., 0], 0.0)
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # A bound too small for the batch (one a world, 4 in all) reads NaN rather than dropping values.
    assert np.isnan(values(score, jnp.asarray(truncated.reshape(t, n)), final_obs, carry, 1)).all() == (truncations > 4)


def test_a_world_truncates_at_most_once_per_step_limit():
    env, params = make("1d-static-step", max_steps=5)
    layout = ObsLayout.from_env(env, params)
    assert [layout.max_truncations(steps) for steps in (1, 5, 6, 64)] == [1, 1, 2, 13]


@pytest.mark.slow
def test_layer_norm_q_network_scan_equals_step_by_step_with_resets():
    env, params = make("1d-static-step")
    net = LayerNormQNetwork(
        ObsLayout.from_env(env, params, previous_step=True), env.num_actions, hidden_size=16, rnn_size=8
    )
    t, b = 7, 3
    key_obs, key_reset, key_init = jax.random.split(jax.random.key(0), 3)
    obs = jax.random.uniform(key_obs, (t, b, net.layout.obs_size), minval=-1, maxval=40)
    resets = jax.random.bernoulli(key_reset, 0.3, (t, b)).at[0].set(True)
    carry0 = jax.random.normal(key_init, (b, 8))  # a stale carry: step 0's reset must clear it
    variables = jax.jit(net.init)(jax.random.key(1), carry0, obs, resets)
    assert any("LayerNorm" in name for name in variables["params"]["ObservationEncoder_0"])

    # Jitted: one program per sequence length (op by op, over a hundred small ones).
    apply = jax.jit(net.apply)
    carry_scan, q_scan = apply(variables, carry0, obs, resets)
    carry = carry0
    for i in range(t):
        carry, q = apply(variables, carry, obs[i : i + 1], resets[i : i + 1])
        np.testing.assert_allclose(q[0], q_scan[i], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(carry, carry_scan, rtol=1e-5, atol=1e-6)
    # A reset really forgets: after the first reset the outputs ignore the carry before it.
    _, q_other = apply(variables, carry0 + 5.0, obs, resets)
    after = np.asarray(resets).cumsum(axis=0) >= 1
    np.testing.assert_allclose(np.asarray(q_other)[after], np.asarray(q_scan)[after], rtol=1e-5, atol=1e-6)
    # A reset inside the sequence forgets the carry the episode before it built: world 0 restarts
    # at step 4, so changing its observations before then changes only its outputs before then.
    resets = jnp.zeros((t, b), bool).at[0].set(True).at[4, 0].set(True)
    changed = obs.at[:4, 0].add(3.0)
    _, q_a = apply(variables, carry0, obs, resets)
    _, q_b = apply(variables, carry0, changed, resets)
    np.testing.assert_allclose(q_b[4:, 0], q_a[4:, 0], rtol=1e-5, atol=1e-6)
    assert not np.allclose(q_b[:4, 0], q_a[:4, 0], atol=1e-4)
    # Without that reset the earlier observations reach the later outputs through the carry.
    _, q_c = apply(variables, carry0, obs, resets.at[4, 0].set(False))
    _, q_d = apply(variables, carry0, changed, resets.at[4, 0].set(False))
    assert not np.allclose(q_d[4:, 0], q_c[4:, 0], atol=1e-4)


def test_other_learners_networks_have_no_layer_norm():
    env, params = make("1d-static-sin")
    net = ActorCritic(ObsLayout.from_env(env, params), env.num_actions, hidden_size=8, rnn_size=4)
    # The parameters' paths need no values: their shapes, traced without compiling anything.
    variables = jax.eval_shape(
        net.init, jax.random.key(0), net.initial_carry(1), jnp.zeros((1, 1, 7)), jnp.ones((1, 1), bool)
    )
    paths = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(variables)[0]]
    assert paths and not any("LayerNorm" in p for p in paths), paths


@pytest.mark.slow
def test_rollout_q_values_equal_a_pass_over_the_sequence_from_the_start_carry(dynamic_recurrent):
    """The targets bootstrap from the rollout's own Q-values: they must be what the learner's
    sequence pass (from the carry at the rollout's start, with resets) computes."""
    pqn, state = dynamic_recurrent
    rollout = jax.jit(pqn.rollout)
    state, _, _ = rollout(state, pqn.env_params)  # a non-zero carry
    carry0 = state.worlds.carry
    _, batch, _ = rollout(state, pqn.env_params)
    assert bool(batch.reset[1:].any()) and bool(batch.truncated.any()) and bool(jnp.abs(carry0).max() > 0)
    _, q = jax.jit(pqn.network.apply)(state.params, carry0, batch.obs, batch.reset)
    np.testing.assert_allclose(q.max(-1), batch.value, rtol=1e-5, atol=1e-6)


# --- training ----------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "agent",
    [
        "static_feed_forward",
        "dynamic_recurrent",
        pytest.param("2d-dynamic-sparse", marks=pytest.mark.slow),  # recurrent; the conv design encoder: a long compile
    ],
)
def test_tiny_training_run_has_finite_losses_and_compiles_once(agent, request):
    if agent == "2d-dynamic-sparse":
        pqn = _pqn(agent, recurrent=True, max_steps=6)
        state = jax.jit(pqn.init)(jax.random.key(0))
    else:
        pqn, state = request.getfixturevalue(agent)
    traces = []

    def chunk(state):
        traces.append(1)
        return pqn.train_chunk(state, pqn.env_params, 2)

    run = jax.jit(chunk)
    state, first = run(state)
    state, metrics = run(state)
    assert len(traces) == 1 and run._cache_size() == 1
    assert metrics["loss"].shape == (2,) and int(state.update) == 4
    for name in ("loss", "q_mean", "target_mean"):
        assert np.all(np.isfinite(metrics[name])), name
    assert int(metrics["episodes"].sum()) > 0
    assert float(first["epsilon"][0]) == 1.0 and float(metrics["epsilon"][-1]) == pytest.approx(0.01)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))


@pytest.mark.slow
def test_staggered_starts_put_the_worlds_at_different_points_of_their_episodes(static_feed_forward):
    """Without staggering every world starts at step 0; with it each world is a random number of
    random steps (below the step limit) into an episode of the task, the same numbers for the same key."""
    plain, state = static_feed_forward
    assert not plain.config.stagger_starts and np.all(np.asarray(state.worlds.env_state.time) == 0)
    staggered = _pqn(num_envs=64, stagger_starts=True)
    init = jax.jit(staggered.init)
    times = np.asarray(init(jax.random.key(0)).worlds.env_state.time)
    limit = int(staggered.env_params.max_steps_in_episode)
    assert np.all((times >= 0) & (times < limit)) and len(np.unique(times)) > 32
    again = np.asarray(init(jax.random.key(0)).worlds.env_state.time)
    np.testing.assert_array_equal(times, again)


@pytest.mark.slow  # about 10 s on the 2-core CPU, cold: `pytest -m slow` (CI runs both)
def test_two_seeds_through_the_driver_differ(tmp_path):
    from agents.training.driver import read_metrics, train

    config = make_config("pqn", "1d-static-sin", **{**TINY, "seeds": 2, "max_steps": 6})
    _, state = train(config, tmp_path, progress=False)
    assert list(np.asarray(state.update)) == [2, 2]
    first = jax.tree.leaves(state.params)[0]
    assert not np.allclose(first[0], first[1])
    lines = read_metrics(tmp_path)
    assert [r["chunk"] for r in lines] == [0, 1] and all(len(r["loss"]) == 2 for r in lines)


@pytest.mark.slow  # two runs and a resume through the driver, with compiles: ~30 s or more on a 2-core CPU
@pytest.mark.parametrize("recurrent", [True, False])
def test_resume_equals_uninterrupted(tmp_path, recurrent):
    from agents.training import checkpoint
    from agents.training.driver import train

    config = make_config(
        "pqn",
        "1d-static-gauss",
        **{**TINY, "recurrent": recurrent, "seeds": 2, "total_steps": 4 * 8 * 8, "chunks": 4, "max_steps": 6},
    )
    _, straight = train(config, tmp_path / "straight", progress=False)
    _, first = train(config, tmp_path / "killed", progress=False, stop_after_chunks=2)
    assert list(np.asarray(first.update)) == [2, 2]
    _, resumed = train(config, tmp_path / "killed", resume=True, progress=False)
    assert list(np.asarray(resumed.update)) == [4, 4]
    a, b = checkpoint.to_storable(straight), checkpoint.to_storable(resumed)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.slow
def test_greedy_policy_runs_in_the_evaluator_with_recurrent_state(dynamic_recurrent):
    pqn, state = dynamic_recurrent
    assert pqn.config.recurrent
    env, params = make("1d-dynamic", test_design=3, max_steps=30)
    episodes = run_episodes(env, params, pqn.policy(state.params), jax.random.key(1), np.zeros(4, np.int32))
    assert episodes.iou.shape == (4,)
    assert np.all((episodes.iou >= 0) & (episodes.iou <= 1))


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(num_envs=30, num_minibatches=4), "multiple of num_minibatches"),
        (dict(q_lambda=1.5), r"q_lambda must be a number in \[0, 1\]"),
        (dict(eps_end=-0.1), r"eps_end must be a number in \[0, 1\]"),
        (dict(learning_rate=0.0), "learning_rate must be a number > 0"),
        (dict(lstm_size=8), "unknown pqn option"),
    ],
)
def test_config_errors_are_clear(options, message):
    with pytest.raises(ValueError, match=message):
        make_config("pqn", "1d-static-sin", **options)


def test_the_paper_has_no_pqn_row_and_the_table_shows_dashes():
    from snac_jax.evaluation import TaskResult
    from snac_jax.paper import load_paper_results, markdown_table, paper_row

    assert paper_row(load_paper_results(), make_config("pqn").paper_method) == {}
    result = TaskResult.from_episodes(
        "1d-static-sin",
        {"sin": np.array([0.5, 0.7])},
        lengths=[10, 12],
        bricks_used=[3, 4],
        returns=[1.0, 2.0],
        seed=0,
        wall_s=0.0,
    )
    row = markdown_table([result], {"1d-static-sin": {}}).splitlines()[-1]
    assert row.startswith("| 1d-static-sin | 2 | 0.600 |") and row.count("—") == 3, row


@pytest.mark.slow  # a training and two evaluation subprocesses
@pytest.mark.parametrize("recurrent", [True, False])
def test_cli_trains_pqn_with_two_seeds_and_evaluates_each_without_a_paper_row(tmp_path, recurrent):
    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "pqn",
        "--recurrent" if recurrent else "--no-recurrent",
        "--task",
        "1d-static-step",
        "--total-steps",
        "256",
        "--num-envs",
        "8",
        "--rollout-steps",
        "8",
        "--num-minibatches",
        "2",
        "--hidden-size",
        "8",
        "--rnn-size",
        "8",
        "--max-steps",
        "40",
        "--chunks",
        "2",
        "--out",
        str(out),
        "--eval-episodes",
        "2",
        "--no-progress",
        "--seeds",
        "2",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "config.json").read_text())
    assert saved["algorithm"] == "pqn" and saved["recurrent"] is recurrent and saved["seeds"] == 2
    assert "(no paper row)" in result.stdout  # a run with its own step limit is not the paper's task
    check_each_seed_evaluates_from_the_checkpoint(result.stdout, out, "1d-static-step", env)


@pytest.mark.slow
def test_make_train_is_one_jittable_function_vmappable_over_seeds():
    """`make_train(config)` gives the whole run as `train(key)`, as PPO's does: jitted and
    vmapped over two seeds, every update runs, and the seeds train apart."""
    from agents.learners.pqn import make_train

    config = make_config("pqn", "1d-static-sin", **dict(TINY, recurrent=True, max_steps=20))
    state, metrics = jax.jit(jax.vmap(make_train(config)))(jax.random.split(jax.random.key(0), 2))
    assert metrics["loss"].shape == (2, config.num_updates) == (2, 2)
    assert np.all(np.isfinite(metrics["loss"])) and np.asarray(state.update).tolist() == [2, 2]
    first = jax.tree.leaves(state.params)[0]
    assert not np.allclose(first[0], first[1])

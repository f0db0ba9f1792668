"""SAC-Discrete: the soft value, critic, actor and temperature losses and the learner's sum of them
against hand computation, which parameters each loss moves, the Polyak target, tiny runs (one
compile per configuration, two seeds through the driver), the greedy policy, resume and the command
line."""

from __future__ import annotations

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.offpolicy import Step
from agents.common.targets import n_step_targets
from agents.learners.sac import actor_loss, critic_loss, soft_values, temperature_loss
from agents.training.registry import build_algorithm, make_config
from tests.helpers import check_each_seed_evaluates_from_the_checkpoint

# Every option a tuned entry could set is pinned here, so retuning never changes the tests.
TINY = dict(
    num_envs=8,
    rollout_steps=8,
    batch_size=16,
    hidden_sizes="16,16",
    learning_starts=0,
    chunks=2,
    gradient_steps=1,
    learning_rate=1e-3,
    total_steps=4 * 64,
    buffer_size=8 * 40,
    max_steps=20,
)

# With pi = (1/2, 1/2) and alpha = 1 / ln 2, alpha log pi(a) = log2(1/2) = -1 for both actions.
HALF = jnp.log(jnp.array([0.5, 0.5]))
ALPHA = 1.0 / math.log(2.0)


def _agent(task="1d-static-sin", **options):
    return build_algorithm(make_config("sac", task, **{**TINY, **options}))


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


# --- the losses ----------------------------------------------------------------------------------


def test_soft_value_and_critic_loss_match_hand_computation_with_a_terminal():
    # Three rows of one world, two actions; rows 0 and 1 get a loss, the episode ends at row 1.
    q_target = jnp.array(
        [
            [[500.0, 500.0], [4.0, 2.0], [1000.0, 1000.0]],  # target critic 1, rows 0..2
            [[500.0, 500.0], [3.0, 6.0], [1000.0, 1000.0]],  # target critic 2
        ]
    )[:, :, None, :]  # (2, T=3, S=1, A=2)
    log_probs = jnp.broadcast_to(HALF, (3, 1, 2))
    rewards = jnp.array([1.0, 2.0, 4.0])[:, None]
    dones = jnp.array([False, True, False])[:, None]
    q = jnp.array(
        [
            [[0.0, 3.75], [4.0, 0.0]],  # critic 1, rows 0 and 1
            [[9.0, 2.25], [0.0, 9.0]],  # critic 2
        ]
    )[:, :, None, :]
    actions = jnp.array([1, 0])[:, None]

    @jax.jit  # one program (op by op, some fifty)
    def compute():
        values = soft_values(q_target, log_probs, ALPHA)
        targets = n_step_targets(rewards, dones, values, 0.5, n=1, length=2)
        losses = [critic_loss(q, actions, targets, mask) for mask in (jnp.ones((2, 1)), jnp.array([[0.0], [1.0]]))]
        grad = jax.grad(critic_loss, argnums=2)(q, actions, targets, jnp.ones((2, 1)))
        return values, targets, n_step_targets(rewards, dones, values, 0.5, n=2, length=1), losses, grad

    values, targets, two_step, (loss, masked_loss), grad = compute()
    # V(row 1) = 0.5 * (min(4, 3) + 1) + 0.5 * (min(2, 6) + 1) = 0.5 * 4 + 0.5 * 3 = 3.5
    np.testing.assert_allclose(values[1, 0], 3.5, rtol=1e-6)

    # y0 = 1 + 0.5 * V(row 1) = 1 + 0.5 * 3.5 = 2.75; y1 = 2 (terminal: row 2's 1000 never counts)
    np.testing.assert_allclose(targets[:, 0], [2.75, 2.0], rtol=1e-6)
    # Two steps of reward from row 0: 1 + 0.5 * 2, then the episode's end cuts the bootstrap.
    np.testing.assert_allclose(two_step[0, 0], 2.0)

    # row 0, action 1: (3.75 - 2.75)^2 + (2.25 - 2.75)^2 = 1 + 0.25 = 1.25
    # row 1, action 0: (4 - 2)^2 + (0 - 2)^2 = 4 + 4 = 8
    np.testing.assert_allclose(loss, (1.25 + 8) / 2, rtol=1e-6)
    np.testing.assert_allclose(masked_loss, 8.0, rtol=1e-6)
    # The targets are held fixed.
    assert not np.any(grad)


def test_actor_loss_matches_hand_computation_and_moves_only_the_policy():
    log_probs = jnp.stack([HALF, jnp.log(jnp.array([0.75, 0.25]))])  # two states
    q = jnp.array(
        [
            [[3.0, 5.0], [4.0, 9.0]],  # critic 1, states 0 and 1
            [[4.0, 1.0], [6.0, 8.0]],  # critic 2
        ]
    )

    @jax.jit  # one program (op by op, some forty)
    def compute():
        losses = (
            actor_loss(log_probs[:1], q[:, :1], ALPHA, jnp.ones(1)),
            actor_loss(log_probs[1:], q[:, 1:], 0.0, jnp.ones(1)),
            actor_loss(log_probs, q, 0.0, jnp.ones(2)),
        )
        return losses, jax.grad(actor_loss, argnums=(0, 1, 2))(log_probs, q, ALPHA, jnp.ones(2))

    (one, two, both), (grad_log_probs, grad_q, grad_alpha) = compute()
    # state 0, alpha = 1/ln 2: min Q = (3, 1); 0.5 * (-1 - 3) + 0.5 * (-1 - 1) = -2 - 1 = -3
    np.testing.assert_allclose(one, -3.0, rtol=1e-6)
    # state 1, alpha = 0: min Q = (4, 8); -(0.75 * 4 + 0.25 * 8) = -(3 + 2) = -5
    np.testing.assert_allclose(two, -5.0, rtol=1e-6)
    # both states with alpha = 0: state 0 gives -(0.5 * 3 + 0.5 * 1) = -2, mean (-2 - 5) / 2 = -3.5
    np.testing.assert_allclose(both, -3.5, rtol=1e-6)
    assert not np.any(grad_q) and float(grad_alpha) == 0.0
    assert np.any(grad_log_probs)


def test_temperature_loss_matches_hand_computation_and_moves_only_alpha():
    log_probs = jnp.stack([HALF, jnp.log(jnp.array([0.75, 0.25]))])
    # H(1/2, 1/2) = ln 2 = 0.693147; H(3/4, 1/4) = 0.75 * 0.287682 + 0.25 * 1.386294 = 0.562335
    # target 0.6: gaps 0.093147 and -0.037665, mean 0.027741; times log alpha = 2: 0.055482
    # One program (op by op, a few): the loss and its gradients in log alpha and in the log-probabilities.
    loss_and_grads = jax.jit(jax.value_and_grad(temperature_loss, argnums=(0, 1)))
    loss, (grad, grad_log_probs) = loss_and_grads(jnp.asarray(2.0), log_probs, 0.6, jnp.ones(2))
    np.testing.assert_allclose(loss, 0.055482, rtol=1e-4)
    # Its gradient is the mean gap: > 0 while the policy is more random than the target, so a
    # descent step lowers alpha; with only the (3/4, 1/4) state it is < 0 and raises alpha.
    np.testing.assert_allclose(grad, 0.027741, rtol=1e-4)
    assert float(loss_and_grads(jnp.asarray(2.0), log_probs, 0.6, jnp.array([0.0, 1.0]))[1][0]) < 0
    assert not np.any(grad_log_probs)


def test_the_learners_loss_combines_the_three_by_hand():
    """`SAC.loss` with the actor and the critics replaced by tables of hand-set outputs, looked up
    by the row index each window's observation carries: which rows, which network (the target
    critics bootstrap), which rewards and which temperature each loss reads."""
    agent = _agent(n_step=1, sequence_length=1, gamma=0.5, reward_scale=2.0)
    c = agent.config.context
    assert agent.env.num_actions == 3 and c == 1  # rows: 0 the context, 1 the learning step, 2 the next
    row = lambda inputs: inputs[..., 0, 0].astype(jnp.int32)  # one window: (rows, 1, O) -> (rows,)
    agent.actor = SimpleNamespace(apply=lambda p, inputs: p[row(inputs)][:, None])  # logits (rows, 1, A)
    agent.critic = SimpleNamespace(apply=lambda p, inputs: p[:, row(inputs)][:, :, None])  # (2, rows, 1, A)
    never = [1e3] * 3  # outputs no loss may read
    params = {
        # The learning row's policy (1/2, 1/4, 1/4); the next row's uniform.
        "actor": jnp.log(jnp.array([[0.9, 0.05, 0.05], [0.5, 0.25, 0.25], [1 / 3, 1 / 3, 1 / 3]])),
        # The critics at the learning row.
        "critic": jnp.array([[never, [5.0, 0.0, 0.0], never], [never, [3.0, 2.0, 8.0], never]]),
        "log_alpha": jnp.log(jnp.asarray(2.0)),
    }
    # The target critics at the next row: minimum (3, 3, 9).
    target = jnp.array([[never, [500.0] * 3, [3.0, 6.0, 9.0]], [never, [500.0] * 3, [6.0, 3.0, 12.0]]])
    rows = c + 2
    obs = jnp.zeros((rows, 1, agent.layout.env_obs_size)).at[:, 0, 0].set(jnp.arange(rows))
    batch = Step(
        obs=obs.astype(jnp.int16),
        reset=jnp.zeros((rows, 1), bool),
        action=jnp.zeros((rows, 1), jnp.int8),
        reward=jnp.zeros((rows, 1)),
        done=jnp.zeros((rows, 1), bool),
    )  # action 0 at the learning row
    rewards = jnp.full((rows, 1), 9.0).at[c].set(0.5)  # learned from as 1 (reward_scale 2)

    # Jitted, one program for both batches below (op by op, over a hundred).
    loss = jax.jit(lambda batch: agent.loss(params, target, batch, obs, rewards, jnp.ones((rows, 1))))
    total, info = loss(batch)
    # alpha = 2. V(next) = sum_a 1/3 (min Q - 2 ln 1/3) = (3 + 3 + 9) / 3 + 2 ln 3 = 7.197225;
    # y = 1 + 0.5 * 7.197225 = 4.598612. Critics at action 0: (5 - y)^2 + (3 - y)^2 = 2.716672.
    # Actor: 1/2 (2 ln 1/2 - 3) + 2 * 1/4 (2 ln 1/4 - 0) = -2.193147 - 1.386294 = -3.579441.
    # Temperature: H(1/2, 1/4, 1/4) = 1.039721, target 0.98 ln 3 = 1.076640; ln 2 * (-0.036919) = -0.025590.
    np.testing.assert_allclose(info["critic_loss"], 2.716672, rtol=1e-5)
    np.testing.assert_allclose(info["actor_loss"], -3.579441, rtol=1e-5)
    np.testing.assert_allclose(info["alpha_loss"], -0.025590, rtol=1e-4)
    np.testing.assert_allclose(total, 2.716672 - 3.579441 - 0.025590, rtol=1e-5)
    np.testing.assert_allclose([info["alpha"], info["entropy"], info["q_mean"]], [2.0, 1.039721, 3.0], rtol=1e-5)
    # The episode ends at the learning row: y = 1, critics (5 - 1)^2 + (3 - 1)^2 = 20.
    ended = batch.replace(done=batch.done.at[c].set(True))
    np.testing.assert_allclose(loss(ended)[1]["critic_loss"], 20.0, rtol=1e-6)


# --- the learner --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def one_update_chunks():
    """A SAC agent (tau 0.25) and its training chunk of one update, jitted once, with a record
    of the loss's traces: the runs below all call this one program."""
    agent = _agent(tau=0.25)
    traces = []
    loss = agent.loss
    agent.loss = lambda *args: (traces.append(1), loss(*args))[1]
    chunk = jax.jit(lambda s: agent.train_chunk(s, agent.env_params, 1))
    return agent, chunk, traces, jax.jit(agent.init)(jax.random.key(0))


@pytest.mark.slow
def test_sac_trains_a_few_updates_with_finite_losses_and_polyak_targets(one_update_chunks):
    agent, chunk, _, state = one_update_chunks
    critics = state.params["critic"]["params"]["VmapActionHead_0"]["Dense_0"]["kernel"]
    assert not np.array_equal(critics[0], critics[1]), "the twin critics start apart"
    assert _same(state.target_params, state.params["critic"])

    after, _ = chunk(state)
    assert int(after.gradient_step) == 1
    # One gradient step: each target moves a quarter of the way to its critic.
    expected = jax.tree.map(lambda t, p: 0.75 * t + 0.25 * p, state.target_params, after.params["critic"])
    for x, y in zip(jax.tree.leaves(after.target_params), jax.tree.leaves(expected)):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)
    for part in ("actor", "critic", "log_alpha"):
        assert not _same(after.params[part], state.params[part]), part

    state, runs = after, []
    for _ in range(4):
        state, metrics = chunk(state)
        runs.append(jax.device_get(metrics))
    metrics = jax.tree.map(lambda *x: np.concatenate(x), *runs)
    for name in ("loss", "critic_loss", "actor_loss", "alpha_loss", "alpha", "entropy", "q_mean"):
        assert runs[0][name].shape == (1,) and metrics[name].shape == (4,), name
        assert np.all(np.isfinite(metrics[name])), name
    assert np.all(metrics["entropy"] <= math.log(agent.env.num_actions) + 1e-6)
    assert int(state.gradient_step) == 5 and int(metrics["episodes"].sum()) > 0
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))


def test_a_chunk_compiles_once(one_update_chunks):
    agent, chunk, traces, state = one_update_chunks
    state, _ = chunk(state)
    first = len(traces)
    state, _ = chunk(state)
    state, _ = chunk(state)
    assert first > 0 and len(traces) == first
    assert chunk._cache_size() == 1


def test_greedy_policy_is_the_argmax_of_the_actors_logits():
    agent = _agent("2d-static-dense")
    env, env_params = agent.env, agent.env_params
    layout = agent.layout
    policy = agent.policy(None)  # its parameters are passed to `act`

    @jax.jit  # a new run's parameters and six steps of an episode as one program (op by op, some seventy)
    def episode(key):
        # The parameters a new run starts from (`init` reads them from `init_params` too).
        params, _ = agent.init_params(key, jnp.zeros((1, 1, 1, layout.obs_size)))
        # Sharpen the actor so that its argmax is unambiguous.
        params["actor"]["params"]["Dense_0"]["kernel"] *= 300.0
        obs, env_state = env.reset(jax.random.key(2), env_params)

        def step(carry, keys):
            obs, env_state, policy_state = carry
            action, new_state = policy.act(params, policy_state, obs, keys[0])
            logits = agent.actor.apply(params["actor"], layout.acting_inputs(obs, policy_state))
            obs, env_state, _, _, _, _ = env.step(keys[1], env_state, action, env_params)
            return (obs, env_state, new_state), (action, jnp.argmax(logits))

        keys = jnp.stack([jax.vmap(jax.random.key)(jnp.arange(6)), jax.vmap(jax.random.key)(10 + jnp.arange(6))], 1)
        return jax.lax.scan(step, (obs, env_state, policy.init(jax.random.key(3), None)), keys)[1]

    actions, greedy = episode(jax.random.key(1))
    assert actions.shape == (6,)
    np.testing.assert_array_equal(actions, greedy)
    assert policy.name == "sac"


@pytest.mark.slow  # a whole driver run (minutes on 2 cores): `pytest -m slow`
def test_two_seeds_through_the_driver(tmp_path):
    from agents.training.checkpoint import read_config
    from agents.training.driver import read_metrics, train
    from agents.training.trained import checkpoint_policy

    config = make_config("sac", "1d-static-step", **{**TINY, "seeds": 2})
    algorithm, state = train(config, tmp_path, progress=False)
    assert read_config(tmp_path) == config
    actor = state.params["actor"]["params"]["Dense_0"]["kernel"]
    assert actor.shape[0] == 2 and not np.array_equal(actor[0], actor[1])
    assert state.params["log_alpha"].shape == (2,)
    records = read_metrics(tmp_path)
    assert len(records) == 2 and all(len(r["critic_loss"]) == 2 and len(r["alpha"]) == 2 for r in records)
    policy = checkpoint_policy(algorithm.env, tmp_path, seed_index=1)
    assert _same(policy.params["actor"], jax.tree.map(lambda x: x[1], state.params["actor"]))


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(hidden_sizes="64,x"), "hidden_sizes must be comma-separated ints >= 1"),
        (dict(hidden_sizes="64,0"), "hidden_sizes must be comma-separated ints >= 1"),
        (dict(tau=0.0), r"tau must be a number in \(0, 1\]"),
        (dict(target_entropy_fraction=1.5), r"target_entropy_fraction must be a number in \[0, 1\]"),
        (dict(initial_alpha=0.0), "initial_alpha must be a number > 0"),
        (dict(eps_end=0.1), "unknown sac option"),
    ],
)
def test_config_errors_are_clear(options, message):
    with pytest.raises(ValueError, match=message):
        make_config("sac", "1d-static-sin", **options)


def test_network_widths_follow_the_papers_appendix_per_dimension():
    assert make_config("sac", "1d-static-sin").layers == (64, 64)
    assert make_config("sac", "1d-dynamic").layers == (64, 64)
    assert make_config("sac", "2d-static-sparse").layers == (64, 128, 64)
    assert make_config("sac", "2d-dynamic-dense").layers == (512, 512, 512)
    assert make_config("sac", "3d-static-dense").layers == (64, 128, 256, 128, 64)
    shapes = jax.eval_shape(build_algorithm(make_config("sac", "2d-static-dense")).init, jax.random.key(0)).params
    for part, lead in (("actor", ()), ("critic", (2,))):  # the critics' parameters carry the twin axis
        net = shapes[part]["params"]
        net = net["VmapActionHead_0"] if part == "critic" else net
        widths = [net["ObservationEncoder_0"][f"Dense_{i}"]["kernel"].shape for i in range(3)]
        assert [w[: len(lead)] for w in widths] == [lead] * 3 and [w[-1] for w in widths] == [64, 128, 64], part
        assert net["Dense_0"]["kernel"].shape[-1] == 5  # one output per 2D action


# --- resume and the command line ------------------------------------------------------------------


@pytest.mark.slow  # three compilations of a whole run through the driver
def test_resume_gives_the_uninterrupted_result_and_the_checkpoint_evaluates(tmp_path):
    from agents.training.driver import train
    from agents.training.trained import checkpoint_policy
    from snac_jax.evaluation import evaluate_task

    config = make_config("sac", "1d-dynamic", **{**TINY, "total_steps": 4 * 64, "chunks": 4})
    _, full = train(config, tmp_path / "full", progress=False)
    train(config, tmp_path / "cut", progress=False, stop_after_chunks=1)
    _, resumed = train(config, tmp_path / "cut", resume=True, progress=False)
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed)):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    result = evaluate_task(
        "1d-dynamic", lambda env: checkpoint_policy(env, tmp_path / "cut"), episodes_per_test_design=2, max_steps=20
    )
    assert result.episodes == 20 and 0.0 <= result.mean <= 1.0


@pytest.mark.slow  # a training and an evaluation subprocess
def test_cli_trains_sac_and_evaluates_it(tmp_path):
    import json
    import os
    import subprocess
    import sys

    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "sac",
        "--task",
        "1d-static-step",
        "--total-steps",
        "512",
        "--num-envs",
        "8",
        "--rollout-steps",
        "8",
        "--batch-size",
        "8",
        "--hidden-sizes",
        "8,8",
        "--buffer-size",
        "256",
        "--learning-starts",
        "0",
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
    assert "replay on device" in result.stderr
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "config.json").read_text())
    assert saved["algorithm"] == "sac" and saved["hidden_sizes"] == "8,8" and saved["seeds"] == 2
    assert "(no paper row)" in result.stdout  # a run with its own step limit is not the paper's task
    check_each_seed_evaluates_from_the_checkpoint(result.stdout, out, "1d-static-step", env)

"""DQN / DRQN / DRQN+HER: sequence replay, burn-in, hindsight relabelling against a replay of the
episode, the target network's schedule, n-step targets and the loss by hand, tiny runs of each
agent, resume, config errors.

Episodes are cut short with the `max_steps` training option so that tiny buffers hold many
episode boundaries.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.networks import stack_frames
from agents.common.offpolicy import Step
from agents.common.targets import n_step_targets
from agents.learners.drqn_her import hindsight_rewards
from agents.training.registry import build_algorithm, make_config

# Every option the tuned per-task defaults set is pinned here, so retuning never changes the tests.
TINY = dict(
    num_envs=8,
    rollout_steps=8,
    batch_size=16,
    hidden_size=16,
    learning_starts=0,
    chunks=2,
    gradient_steps=1,
    frame_stack=1,
    learning_rate=1e-3,
)
RECURRENT = dict(lstm_size=16, burn_in=4, sequence_length=6)


def _agent(algorithm, task="1d-static-sin", **options):
    extra = RECURRENT if algorithm != "dqn" else {}
    return build_algorithm(make_config(algorithm, task, **{**TINY, **extra, **options}))


def _run(agent, updates, seed=0):
    """`updates` iterations of `agent` from `init`, jitted as one chunk."""
    state = jax.jit(agent.init)(jax.random.key(seed))
    return jax.jit(lambda s: agent.train_chunk(s, agent.env_params, updates))(state)


@pytest.fixture(scope="module")
def her_1d():
    """A DRQN+HER run on 12-step episodes with random actions; its buffer has wrapped around."""
    agent = _agent(
        "drqn-her",
        total_steps=10 * 64,
        buffer_size=8 * 40,
        max_steps=12,
        eps_start=1.0,
        eps_end=1.0,
        hindsight_fraction=1.0,
    )
    state, _ = _run(agent, 10)
    assert bool(state.buffer.is_full)
    return agent, state


@pytest.fixture(scope="module")
def dqn_updates():
    """A DQN run stepped one jitted update at a time (one program for the target network's
    schedule and the tiny run alike): the agent, the states before and after each update, and
    the updates' metrics stacked."""
    agent = _agent(
        "dqn",
        "1d-static-gauss",
        frame_stack=3,
        n_step=2,
        target_update_interval=3,
        total_steps=7 * 64,
        buffer_size=8 * 40,
        max_steps=20,
    )
    states = [jax.jit(agent.init)(jax.random.key(0))]
    update = jax.jit(lambda s: agent.update(s, agent.env_params))
    metrics = []
    for _ in range(7):
        state, info = update(states[-1])
        states.append(state)
        metrics.append(jax.device_get(info))
    return agent, states, jax.tree.map(lambda *x: np.stack(x), *metrics)


@pytest.fixture(scope="module")
def drqn_run():
    """A plain DRQN run (no double Q, no dueling heads) on 9-step episodes; its buffer has wrapped around."""
    agent = _agent(
        "drqn",
        "2d-static-sparse",
        double_q=False,
        dueling=False,
        total_steps=6 * 64,
        buffer_size=8 * 30,
        max_steps=9,
    )
    state, metrics = _run(agent, 6)
    return agent, state, jax.device_get(metrics)


# --- pure pieces -------------------------------------------------------------------------------------


def test_n_step_targets_match_hand_computation():
    gamma = 0.5
    rewards = jnp.array([1.0, 2.0, 4.0, 8.0, 16.0])[:, None]
    dones = jnp.array([False, True, False, False, False])[:, None]
    values = jnp.array([100.0, 200.0, 300.0, 400.0, 500.0])[:, None]
    targets = n_step_targets(rewards, dones, values, gamma, n=2, length=3)
    expected = [
        1.0 + 0.5 * 2.0,  # the episode ends at step 1: no bootstrap
        2.0,  # ends right here
        4.0 + 0.5 * 8.0 + 0.25 * 500.0,  # two rewards, then the value two steps on
    ]
    np.testing.assert_allclose(targets[:, 0], expected)


def test_loss_matches_hand_computation_with_double_q_an_episode_end_and_a_mask():
    """`DQN.loss` on hand-set Q-values (the network is replaced by them): the double-Q bootstrap,
    the Huber loss, the episode end and the loss mask's weighted mean."""
    agent = _agent("dqn", n_step=1, sequence_length=1, gamma=0.5, reward_scale=2.0, huber_delta=1.0)
    c = agent.config.context
    # Q-values (rows: the learning step, the step after it; 2 windows; 3 actions), as the
    # online network (`params`) and the target network (`target_params`) give them.
    online = jnp.array([[[0.5, 0.0, 9.0], [9.0, 9.0, 0.0]], [[1.0, 3.0, 0.0], [7.0, 7.0, 7.0]]])
    target = jnp.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[5.0, 2.0, 0.0], [7.0, 7.0, 7.0]]])
    agent.replayed_frames = lambda batch, obs: (None, None)
    agent.sequence_q = lambda params, frames, resets: params

    rows = c + 2
    column = lambda *values: jnp.zeros((rows, 2)).at[c].set(jnp.array(values))
    batch = Step(
        obs=jnp.zeros((rows, 2, 1), jnp.int16),
        reset=jnp.zeros((rows, 2), bool),
        action=column(0, 2).astype(jnp.int8),
        reward=column(9.0, 9.0),
        done=column(0, 1).astype(bool),
    )
    # The rewards the loss learns from (hindsight relabels them, not batch.reward), as 1 and 0.4
    # after reward_scale 2.
    rewards = column(0.5, 0.2)

    # Jitted (one program per config, not one per operation); the config is read when it traces.
    jitted_loss = lambda: jax.jit(lambda mask: agent.loss(online, target, batch, None, rewards, mask))
    loss_of = jitted_loss()
    loss, info = loss_of(jnp.ones((rows, 2)))
    # Window 0: the online network picks action 1 at the next step (3 > 1; not its choice 2 at the
    # learning step), the target network
    # values it 2: y = 1 + 0.5 * 2 = 2; Q(s, 0) = 0.5, error 1.5, Huber (delta 1) 1.5 - 0.5 = 1.
    # Window 1: the episode ends: y = 0.4; Q(s, 2) = 0, error 0.4, Huber 0.4^2 / 2 = 0.08.
    np.testing.assert_allclose(loss, (1.0 + 0.08) / 2, rtol=1e-6)
    np.testing.assert_allclose(info["q_mean"], (0.5 + 0.0) / 2, rtol=1e-6)
    loss, _ = loss_of(column(1, 0))  # window 1 masked out
    np.testing.assert_allclose(loss, 1.0, rtol=1e-6)
    # Without double Q the target network's own maximum 5: y = 3.5, error 3, Huber 3 - 0.5 = 2.5.
    agent.config = dataclasses.replace(agent.config, double_q=False)
    loss, _ = jitted_loss()(jnp.ones((rows, 2)))
    np.testing.assert_allclose(loss, (2.5 + 0.08) / 2, rtol=1e-6)


def test_stacked_frames_are_zero_before_the_episode_start():
    obs = jnp.arange(1.0, 6.0)[:, None, None]  # 5 steps, one world, one feature
    resets = jnp.array([False, False, True, False, False])[:, None]
    frames = stack_frames(obs, resets, 3)[:, 0, :, 0]
    np.testing.assert_array_equal(frames, [[0, 0, 3], [0, 3, 4], [3, 4, 5]])


# --- replay --------------------------------------------------------------------------------------------


def _check_windows_keep_episodes_apart(agent, state, key):
    batch = jax.device_get(jax.jit(agent.buffer.sample)(state.buffer, key).experience)
    counter = batch.obs[..., agent.layout.window_size + 1].astype(int)  # N_s of each observation
    reset, done = batch.reset, batch.done
    # A new episode inside a window always carries a reset flag exactly after the step that ended
    # the previous one, and the step counter restarts there; otherwise it counts on by one.
    np.testing.assert_array_equal(reset[:, 1:], done[:, :-1])
    np.testing.assert_array_equal(counter[:, 1:], np.where(reset[:, 1:], 0, counter[:, :-1] + 1))
    assert reset[:, 1:].any(), "the windows should cross episode boundaries for this check to mean something"
    return batch


@pytest.mark.slow
def test_sampled_sequences_never_mix_episodes_without_a_reset_flag(her_1d):
    agent, state = her_1d
    for i in range(3):
        batch = _check_windows_keep_episodes_apart(agent, state, jax.random.key(i))
        # One world per window; the episode counter moves on exactly at reset flags.
        assert (batch.world == batch.world[:, :1]).all()
        np.testing.assert_array_equal(batch.episode[:, 1:] - batch.episode[:, :-1], batch.reset[:, 1:].astype(int))


@pytest.mark.slow
def test_sequences_of_a_plain_drqn_buffer_keep_episodes_apart(drqn_run):
    agent, state, _ = drqn_run
    assert bool(state.buffer.is_full)
    _check_windows_keep_episodes_apart(agent, state, jax.random.key(7))


@pytest.mark.slow
def test_burn_in_steps_carry_no_gradient(her_1d):
    agent, state = her_1d
    batch, obs, rewards, mask = jax.jit(agent.sample)(state, jax.random.key(3))
    burn_in, first_trained = agent.burn_in, agent.config.context  # rows: previous step, burn-in, trained
    assert agent.layout.num_actions and first_trained == 1 + burn_in, "the fixture should read the previous step"
    # Jitted, the loss and its gradient as one program (op by op they compile some 300 small ones).
    loss_and_grad = jax.jit(
        jax.value_and_grad(lambda o: agent.loss(state.params, state.target_params, batch, o, rewards, mask)[0])
    )
    loss = lambda o: loss_and_grad(o)[0]
    grad = np.asarray(loss_and_grad(obs)[1])
    assert np.abs(grad[: first_trained - 1]).max() == 0.0
    # The last burn-in observation reaches the first trained step only as its previous window.
    assert np.abs(grad[first_trained - 1, ..., agent.layout.window_size :]).max() == 0.0
    assert np.abs(np.asarray(grad[first_trained:])).max() > 0.0
    # The burn-in does warm the state: changing its observations changes the loss (in windows
    # without a reset right after the burn-in).
    bumped = obs.at[1 : first_trained - 1].add(3.0)
    assert float(loss(bumped)) != float(loss(obs))


# --- hindsight ------------------------------------------------------------------------------------------


def _replayer(env, length):
    """`replay(params, design, max_bricks, actions, strides)`: the rewards of replaying `actions`
    with `strides` from reset on `design` (its budget kept), and the state after them. Jitted, one
    program per environment (op by op, the steps compile some ninety small ones): the episode is
    padded to the window's `length`, and the state stays as it was past its end."""

    def replay(params, design, max_bricks, actions, strides, steps):
        params = params.replace(
            designs=design.astype(jnp.int16)[None],
            design_max_bricks=max_bricks.astype(jnp.int32)[None],
            design_volume=jnp.sum(design).astype(jnp.int32)[None],
        )
        _, state = env.reset_to_design(jax.random.key(0), params, 0)

        def step(state, inputs):
            t, action, stride = inputs
            _, after, reward, _, _ = env.step_with_stride(state, action, stride, params)
            on = t < steps
            return jax.tree.map(lambda a, b: jnp.where(on, a, b), after, state), reward

        state, rewards = jax.lax.scan(step, state, (jnp.arange(length), actions, strides))
        return rewards, state

    jitted = jax.jit(replay)

    def run(params, design, max_bricks, actions, strides):
        steps = len(actions)
        pad = lambda x, fill: np.concatenate([np.asarray(x, np.int32), np.full(length - steps, fill, np.int32)])
        rewards, state = jitted(
            params, jnp.asarray(design), jnp.asarray(max_bricks), pad(actions, 0), pad(strides, 1), steps
        )
        return np.asarray(rewards)[:steps], state

    return run


def _check_relabelled_rewards_equal_replay(agent, state, key):
    env, cfg = agent.env, agent.env.config
    batch, obs, rewards, mask = jax.device_get(jax.jit(agent.sample)(state, key))
    batch = jax.tree.map(lambda x: np.asarray(x).swapaxes(0, 1), batch)  # back to (S, L)
    obs, rewards, mask = (np.asarray(x).swapaxes(0, 1) for x in (obs, rewards, mask))
    ring = jax.device_get(state.worlds.final_grids)
    _replay = _replayer(env, batch.reward.shape[1])
    checked = 0
    for s in range(batch.reward.shape[0]):
        starts = np.flatnonzero(batch.reset[s])
        for start in starts:
            ends = np.flatnonzero(batch.done[s, start:])
            if not len(ends):
                continue
            end = start + ends[0]
            world, episode = batch.world[s, start], batch.episode[s, start]
            slot = episode % agent.ring_size
            assert ring.episode[world, slot] == episode
            final_grid = ring.grids[world, slot]
            steps = slice(start, end + 1)
            if agent.layout.dynamic:
                offset = agent.layout.window_size + 2
                design = batch.obs[s, start, offset : offset + agent.layout.design_size].reshape(cfg.plan_shape)
                np.testing.assert_array_equal(
                    obs[s, steps, offset : offset + agent.layout.design_size],
                    np.broadcast_to(final_grid.reshape(-1), (end + 1 - start, final_grid.size)),
                )
            else:
                design = np.asarray(agent.env_params.designs[0])
            max_bricks = int(np.asarray(agent.env_params.design_max_bricks)[0]) if not agent.layout.dynamic else None
            if max_bricks is None:
                from snac_jax.tasks import make_params, task_spec

                max_bricks = int(make_params(design[None], task_spec(cfg.task_id).dim).design_max_bricks[0])
            actions, strides = batch.action[s, steps], batch.stride[s, steps]
            # The environment's own rewards and final grid come back from a replay on the design...
            original, final_state = _replay(agent.env_params, design, max_bricks, actions, strides)
            np.testing.assert_array_equal(original, batch.reward[s, steps])
            (pr, pc), (h, w) = cfg.pad, cfg.plan_shape
            np.testing.assert_array_equal(np.asarray(final_state.grid)[pr : pr + h, pc : pc + w], final_grid)
            # ... and the relabelled rewards equal a replay against the final grid as the design.
            relabelled, _ = _replay(agent.env_params, final_grid, max_bricks, actions, strides)
            np.testing.assert_array_equal(rewards[s, steps], relabelled)
            assert mask[s, steps].all()
            checked += 1
    assert checked > 0
    return checked


def test_hindsight_rewards_equal_replaying_against_the_final_grid(her_1d):
    agent, state = her_1d
    _check_relabelled_rewards_equal_replay(agent, state, jax.random.key(11))


@pytest.mark.slow
@pytest.mark.parametrize("task", [pytest.param("2d-static-dense", marks=pytest.mark.slow), "1d-dynamic"])
def test_hindsight_relabelling_in_2d_and_on_dynamic_designs(task):
    agent = _agent(
        "drqn-her",
        task,
        total_steps=6 * 64,
        buffer_size=8 * 40,
        max_steps=14,
        eps_start=1.0,
        eps_end=1.0,
        hindsight_fraction=1.0,
        burn_in=2,
        sequence_length=14,
        batch_size=8,
    )
    state, _ = _run(agent, 6)
    _check_relabelled_rewards_equal_replay(agent, state, jax.random.key(2))


def test_hindsight_rewards_use_the_environment_reward():
    """Direct check of `hindsight_rewards` on hand-made records: height vs design height."""
    from snac_jax.tasks import make

    env, _ = make("1d-static-sin")
    design = jnp.array([[3, 1, 0, 2]])
    cells = jnp.array([0, 1, 2, -1])
    heights = jnp.array([3, 2, 1, 7], jnp.int16)
    rewards = hindsight_rewards(env.config, cells, heights, jnp.broadcast_to(design, (4, 1, 4)))
    np.testing.assert_array_equal(rewards, [10.0, -1.0, -1.0, 0.0])


# --- target network, runs, resume, errors ---------------------------------------------------------


def test_target_network_updates_on_schedule(dqn_updates):
    agent, states, _ = dqn_updates
    assert agent.config.target_update_interval == 3 and agent.config.first_learning_update() == 1
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    for previous, state in zip(states[:-1], states[1:]):
        step = int(state.gradient_step)
        assert step == int(previous.gradient_step) + 1
        assert not same(state.params, previous.params)
        if step % 3 == 0:
            assert same(state.target_params, state.params), step
        else:
            assert same(state.target_params, previous.target_params), step
            assert not same(state.target_params, state.params), step


def test_annealed_learning_rate_decays_linearly_over_the_runs_gradient_steps():
    # 4 updates of 8 worlds x 8 steps, 2 gradient steps each: 8 gradient steps, 1e-3 down to 0.
    options = dict(total_steps=4 * 64, gradient_steps=2, buffer_size=8 * 40)
    constant, annealed = _agent("dqn", **options), _agent("dqn", anneal_lr=True, **options)
    schedule = annealed.learning_rate_schedule()
    np.testing.assert_allclose([schedule(k) for k in (0, 2, 6, 8, 9)], [1e-3, 7.5e-4, 2.5e-4, 0.0, 0.0], atol=1e-12)
    assert constant.learning_rate_schedule() == 1e-3
    # The optimiser applies it: with the same gradient every step, Adam's k-th step (from 0) is the
    # constant rate's times 1 - k/8.
    params, grads = {"w": jnp.ones(3)}, {"w": jnp.array([0.1, -0.2, 0.3])}

    def step(agent, k):
        state = agent.optimizer.init(params)
        for _ in range(k + 1):
            updates, state = agent.optimizer.update(grads, state, params)
        return updates["w"]

    for k in (0, 3, 7):
        np.testing.assert_allclose(step(annealed, k), (1 - k / 8) * step(constant, k), rtol=1e-5)
    assert np.all(np.asarray(step(annealed, 3)) != 0)


def _tiny_drqn_her_2d_dynamic():
    agent = _agent("drqn-her", "2d-dynamic-dense", total_steps=4 * 64, buffer_size=8 * 40, max_steps=20)
    state, metrics = _run(agent, 4)
    return agent, state, metrics


@pytest.mark.slow
@pytest.mark.parametrize(
    "run",
    [
        "dqn",  # 1d-static-gauss, frame_stack 3, n-step 2: the shared `dqn_updates` run
        "drqn",  # 2d-static-sparse, no double Q, no dueling heads: the shared `drqn_run`
        pytest.param("drqn-her", marks=pytest.mark.slow),  # 2d-dynamic-dense
    ],
)
def test_tiny_run_of_each_agent_completes(run, request):
    if run == "dqn":
        agent, states, metrics = request.getfixturevalue("dqn_updates")
        state = states[-1]
    elif run == "drqn":
        agent, state, metrics = request.getfixturevalue("drqn_run")
    else:
        agent, state, metrics = _tiny_drqn_her_2d_dynamic()
    updates = int(state.update)
    assert metrics["loss"].shape == (updates,) and updates > 1
    assert np.all(np.isfinite(metrics["loss"])) and np.all(np.isfinite(metrics["q_mean"]))
    # Learning waits for one window.
    assert int(state.gradient_step) == updates - int((agent.config.sample_length - 1) // 8)
    assert int(metrics["episodes"].sum()) > 0
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))


@pytest.mark.slow  # three compilations of a whole run: ~100 s on a 2-core CPU (PPO's resume test stays in the default suite)
def test_resume_gives_the_uninterrupted_result_and_the_checkpoint_evaluates(tmp_path):
    from agents.training.driver import train
    from agents.training.trained import checkpoint_policy
    from snac_jax.evaluation import evaluate_task

    config = make_config(
        "drqn-her", "1d-dynamic", **TINY, **RECURRENT, total_steps=4 * 64, buffer_size=8 * 30, max_steps=10
    )
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


@pytest.mark.parametrize(
    "algorithm,options,message",
    [
        ("dqn", dict(buffer_size=100, num_envs=64), "buffer_size \\(100\\) holds 1 steps per world"),
        ("drqn", dict(burn_in=-1), "burn_in must be an int >= 0"),
        ("drqn-her", dict(hindsight_fraction=1.5), "hindsight_fraction must be a number in \\[0, 1\\]"),
        ("dqn", dict(lstm_size=8), "unknown dqn option"),
        ("drqn", dict(eps_end=-0.1), "eps_end must be a number in \\[0, 1\\]"),
    ],
)
def test_config_errors_are_clear(algorithm, options, message):
    with pytest.raises(ValueError, match=message):
        make_config(algorithm, "1d-static-sin", **options)


def test_replay_memory_is_bounded_by_the_config():
    with pytest.raises(ValueError, match="exceeds max_buffer_mb"):
        build_algorithm(make_config("drqn", "2d-dynamic-dense", buffer_size=2_000_000, max_buffer_mb=100.0))
    agent = build_algorithm(make_config("drqn", "1d-static-sin", buffer_size=100_000, num_envs=100))
    # int16 observations (7) + reset + action + float32 reward + done per step
    per_step = 7 * 2 + 1 + 1 + 4 + 1
    assert 100_000 * per_step <= agent.memory_bytes()["buffer"] <= 100_000 * per_step + 16


def test_replayed_windows_read_the_previous_step_from_the_row_before():
    agent = _agent("drqn")
    layout = agent.layout
    o = layout.env_obs_size
    obs = jnp.arange(4 * o, dtype=jnp.float32).reshape(4, 1, o)  # (L, S, O), distinct rows
    actions = jnp.array([2, 0, 1, 2], jnp.int8)[:, None]
    resets = jnp.array([False, False, True, False])[:, None]
    inputs = np.asarray(agent.network_inputs(obs, actions, resets))[:, 0]
    w, a = layout.window_size, layout.num_actions
    # Row 1 reads row 0's window and action; row 3 reads row 2's.
    np.testing.assert_array_equal(inputs[1, o : o + w], obs[0, 0, :w])
    assert inputs[1, o + w :].argmax() == 2 and inputs[3, o + w :].argmax() == 1
    # Row 0 (nothing before it in the window) and row 2 (an episode start) read "no previous step".
    for t in (0, 2):
        np.testing.assert_array_equal(inputs[t, o : o + w], obs[t, 0, :w])
        assert inputs[t, o + w :].argmax() == a


# Each is a training and an evaluation subprocess (~45 s): `pytest -m slow` (test_train_driver runs PPO's in the default suite).
@pytest.mark.parametrize(
    "algorithm", [pytest.param(name, marks=pytest.mark.slow) for name in ("dqn", "drqn", "drqn-her")]
)
def test_cli_trains_each_value_based_agent_and_evaluates_it(algorithm, tmp_path):
    import json
    import os
    import subprocess
    import sys

    out = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        algorithm,
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
        "--hidden-size",
        "8",
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
    ]
    if algorithm != "dqn":
        cmd += ["--lstm-size", "8", "--burn-in", "2", "--sequence-length", "4"]
    result = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "replay on device" in result.stderr
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    assert json.loads((out / "config.json").read_text())["algorithm"] == algorithm
    assert "| 1d-static-step |" in result.stdout
    again = subprocess.run(
        [sys.executable, "-m", "snac_jax.cli", "eval", "--checkpoint", str(out), "--episodes", "2"],
        capture_output=True,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
        timeout=600,
    )
    assert again.returncode == 0 and "| 1d-static-step |" in again.stdout, again.stderr[-3000:]


def test_hindsight_share_is_smaller_where_the_design_is_not_observed():
    # Static tasks hide the design, so relabelled episodes are kept to a fifth of each batch;
    # dynamic tasks, which observe the design, keep the class default of half.
    assert make_config("drqn-her", "1d-static-gauss").hindsight_fraction == 0.2
    assert make_config("drqn-her", "2d-static-sparse").hindsight_fraction == 0.2
    assert make_config("drqn-her", "1d-dynamic").hindsight_fraction == 0.5
    assert make_config("drqn-her", "1d-static-gauss", hindsight_fraction=0.7).hindsight_fraction == 0.7

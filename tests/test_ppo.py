"""PPO: GAE by hand, the recurrent core against step-by-step application, tiny training runs,
config errors, and the policy the evaluator runs."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.inputs import ObsLayout
from agents.common.networks import ActorCritic
from agents.common.targets import gae
from agents.learners.ppo import PPO, PPOConfig, make_train
from agents.training.registry import config_from_json, make_config
from snac_jax.evaluation import run_episodes
from snac_jax.tasks import make

TINY = dict(
    total_steps=2 * 32 * 16,
    num_envs=32,
    rollout_steps=16,
    num_minibatches=2,
    update_epochs=2,
    hidden_size=16,
    rnn_size=16,
)


def test_gae_matches_hand_computation_with_truncation_and_termination():
    gamma, lam = 0.9, 0.5
    # One world, 4 steps: step 1 is truncated (bootstraps from its final observation's value 5),
    # step 3 terminates (bootstraps nothing).
    rewards = jnp.array([1.0, 2.0, 0.0, 3.0])[:, None]
    values = jnp.array([0.5, 1.0, 2.0, 4.0])[:, None]
    next_values = jnp.array([1.0, 5.0, 4.0, 7.0])[:, None]  # [V(o1), V(final o), V(o3), ignored]
    terminated = jnp.array([0.0, 0.0, 0.0, 1.0])[:, None]
    done = jnp.array([False, True, False, True])[:, None]
    advantages, targets = gae(rewards, values, next_values, terminated, done, gamma, lam)

    d3 = 3.0 - 4.0  # terminated: no bootstrap
    d2 = 0.0 + 0.9 * 4.0 - 2.0
    d1 = 2.0 + 0.9 * 5.0 - 1.0  # truncated: bootstrap from the final observation
    d0 = 1.0 + 0.9 * 1.0 - 0.5
    a3 = d3
    a2 = d2 + gamma * lam * a3
    a1 = d1  # the episode ended at step 1: the trace stops
    a0 = d0 + gamma * lam * a1
    np.testing.assert_allclose(advantages[:, 0], [a0, a1, a2, a3], rtol=1e-6)
    np.testing.assert_allclose(targets[:, 0], np.array([a0, a1, a2, a3]) + np.array([0.5, 1.0, 2.0, 4.0]), rtol=1e-6)


# Fewer truncations than the 4 worlds; more, which a step limit of 3 allows (two a world in 6 steps).
@pytest.mark.slow
@pytest.mark.parametrize("truncations, max_steps", [(3, 750), (7, 3)])
def test_truncation_bootstrap_values_score_the_final_observations_with_the_carry_that_saw_them(truncations, max_steps):
    config = dict(TINY, num_envs=4, rollout_steps=6, max_steps=max_steps)
    ppo = PPO(make_config("ppo", "1d-static-sin", recurrent=True, **config))
    state = jax.jit(ppo.init)(jax.random.key(0))
    _, batch, _ = jax.jit(ppo.rollout)(state, ppo.env_params)
    t, n = batch.reward.shape
    chosen = np.random.default_rng(truncations).choice(t * n, size=truncations + 2, replace=False)
    done = np.zeros(t * n, bool)
    done[chosen] = True
    terminated = np.zeros(t * n, bool)
    terminated[chosen[:2]] = True  # two terminations: no bootstrap value
    batch = batch._replace(done=jnp.asarray(done.reshape(t, n)), terminated=jnp.asarray(terminated.reshape(t, n)))

    got = np.asarray(jax.jit(ppo._final_values)(state.params, batch)).reshape(-1)

    apply = jax.jit(ppo.network.apply)  # one program for every world's value, not one per operation
    expected = np.zeros(t * n, np.float32)
    for i in chosen[2:]:
        step, world = divmod(int(i), n)
        _, _, value = apply(
            state.params,
            batch.carry_after[step, world][None],
            batch.final_obs[step, world][None, None],
            jnp.zeros((1, 1), bool),
        )
        expected[i] = float(value[0, 0])
    assert np.count_nonzero(expected) == truncations
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


def test_network_inputs_one_hot_heights_and_the_previous_step():
    env, params = make("1d-static-sin")  # window of 5, 3 actions, tallest design cell 30
    layout = ObsLayout.from_env(env, params, previous_step=True)
    obs = jnp.array([-1.0, 0.0, 20.0, 31.0, 57.0, 7.0, 9.0])  # window, N_b, N_s
    previous = jnp.array([0.0, 20.0, 31.0, 57.0, 3.0, 6.0, 8.0])
    classes = np.asarray(layout.height_classes(obs[:5]))
    # classes: landmark -2, padding -1, heights 0..30, one "taller" class shared by 31 and 57
    assert classes.shape == (5, 34) and (classes.sum(-1) == 1).all()
    assert [int(c.argmax()) for c in classes] == [1, 2, 22, 33, 33]

    later = layout.with_previous_step(obs, previous, jnp.int32(1), jnp.bool_(False))
    assert later.shape == (layout.obs_size,) == (7 + 5 + 4,)
    np.testing.assert_array_equal(later[7:12], previous[:5])
    np.testing.assert_array_equal(later[12:], [0, 1, 0, 0])
    # An episode's first observation has no previous step: its own window and action "none".
    first = layout.with_previous_step(obs, previous, jnp.int32(1), jnp.bool_(True))
    np.testing.assert_array_equal(first[7:12], obs[:5])
    np.testing.assert_array_equal(first[12:], [0, 0, 0, 1])
    parts = layout.split(later)
    np.testing.assert_allclose(parts["previous_window"][0], previous[:5] / 30.0)
    np.testing.assert_array_equal(parts["last_action"], [0, 1, 0, 0])
    assert ObsLayout.from_env(env, params).obs_size == 7


@pytest.mark.slow
def test_scanned_recurrent_network_equals_step_by_step_with_resets():
    env, params = make("1d-static-step")
    net = ActorCritic(ObsLayout.from_env(env, params), env.num_actions, hidden_size=16, rnn_size=8)
    t, b = 7, 3
    key_obs, key_reset, key_init = jax.random.split(jax.random.key(0), 3)
    obs = jax.random.uniform(key_obs, (t, b, env.observation_layout.size), minval=-1, maxval=40)
    resets = jax.random.bernoulli(key_reset, 0.3, (t, b)).at[0].set(True)
    carry0 = jax.random.normal(key_init, (b, 8))  # a stale carry: step 0's reset must clear it
    variables = jax.jit(net.init)(jax.random.key(1), carry0, obs, resets)
    apply = jax.jit(net.apply)  # one program for the sequence and one for a step, not one per operation

    carry_scan, logits_scan, value_scan = apply(variables, carry0, obs, resets)
    carry = carry0
    for i in range(t):
        carry, logits, value = apply(variables, carry, obs[i : i + 1], resets[i : i + 1])
        np.testing.assert_allclose(logits[0], logits_scan[i], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(value[0], value_scan[i], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(carry, carry_scan, rtol=1e-5, atol=1e-6)

    # A reset really forgets: the outputs after a reset do not depend on the carry before it.
    _, logits_other, _ = apply(variables, carry0 + 5.0, obs, resets)
    after_first_reset = np.asarray(resets).cumsum(axis=0) >= 1
    np.testing.assert_allclose(
        np.asarray(logits_other)[after_first_reset], np.asarray(logits_scan)[after_first_reset], rtol=1e-5, atol=1e-6
    )


@functools.cache
def tiny_training(task: str, recurrent: bool):
    """Two seeds of a tiny training, `make_train` jitted and vmapped over them: one program per
    configuration, compiled once for the tests that read its outputs."""
    config = make_config("ppo", task, recurrent=recurrent, **TINY)
    state, metrics = jax.jit(jax.vmap(make_train(config)))(jax.random.split(jax.random.key(0), 2))
    return config, state, metrics


@pytest.mark.slow
@pytest.mark.parametrize(
    "task,recurrent",
    [
        pytest.param("1d-static-sin", False, marks=pytest.mark.slow),
        ("1d-static-sin", True),
        pytest.param("2d-dynamic-sparse", True, marks=pytest.mark.slow),
    ],
)
def test_tiny_training_run_has_finite_losses(task, recurrent):
    config, state, metrics = tiny_training(task, recurrent)
    assert metrics["loss"].shape == (2, config.num_updates)
    for name in ("loss", "value_loss", "actor_loss", "entropy", "approx_kl"):
        assert np.all(np.isfinite(metrics[name])), name
    np.testing.assert_array_equal(state.update, [config.num_updates] * 2)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))


def test_train_is_vmappable_over_seeds_and_seeds_differ():
    config, state, metrics = tiny_training("1d-static-sin", True)  # the run above: one training compiled
    assert metrics["loss"].shape == (2, config.num_updates)
    first = jax.tree.leaves(state.params)[0]
    assert not np.allclose(first[0], first[1])


# 40 steps place at most 40 of the step design's 600 bricks: IoU <= 40 / 600 = 0.067. Dropping
# every step on the start column (the untrained greedy policy may) scores 25 / 615 = 0.041.
SHORT_EPISODE_BAR = 0.85 * 40 / 600


@pytest.mark.slow
def test_ppo_learns_on_a_short_episode_task():
    """A learning-threshold check: with 40-step episodes on the 1D step design, a few hundred
    thousand steps must come close to the best IoU 40 steps allow (SHORT_EPISODE_BAR)."""
    config = make_config(
        "ppo",
        "1d-static-step",
        recurrent=False,
        update_epochs=4,
        num_minibatches=4,
        reward_scale=0.1,
        ent_coef_end=0.01,
        total_steps=300_000,
        num_envs=64,
        rollout_steps=40,
        hidden_size=32,
        learning_rate=3e-3,
        max_steps=40,
    )
    ppo = PPO(config)

    def greedy_iou(params):
        policy = ppo.policy(params)
        episodes = run_episodes(ppo.env, ppo.env_params, policy, jax.random.key(5), np.zeros(64, np.int32))
        return float(np.mean(episodes.iou))

    state = jax.jit(ppo.init)(jax.random.key(0))
    before = greedy_iou(state.params)
    state, metrics = jax.jit(lambda s: ppo.train_chunk(s, ppo.env_params, config.num_updates))(state)
    after = greedy_iou(state.params)
    assert after > SHORT_EPISODE_BAR and after > before, (before, after)


@pytest.mark.slow
def test_policy_runs_in_the_evaluator_with_recurrent_state():
    config = make_config("ppo", "1d-dynamic", recurrent=True, **TINY)
    ppo = PPO(config)
    state = jax.jit(ppo.init)(jax.random.key(0))
    env, params = make("1d-dynamic", test_design=3, max_steps=30)
    episodes = run_episodes(env, params, ppo.policy(state.params), jax.random.key(1), np.zeros(4, np.int32))
    assert episodes.iou.shape == (4,)
    assert np.all((episodes.iou >= 0) & (episodes.iou <= 1))


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(num_envs=30, num_minibatches=4), "multiple of num_minibatches"),
        (dict(gamma=1.5), "gamma must be a number in [0, 1]"),
        (dict(learning_rate=0.0), "learning_rate must be a number > 0"),
        (dict(total_steps=0), "total_steps must be an int >= 1"),
        (dict(recurrent="yes"), "recurrent must be True or False"),
        (dict(rollout_length=3), "unknown ppo option"),
        (dict(ent_coef_end=-1.5), "ent_coef_end must be a number >= -1 or None"),
    ],
)
def test_config_errors_are_clear(options, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        make_config("ppo", "1d-static-sin", **options)


def test_entropy_coefficient_anneals_linearly_to_its_end_value():
    config = make_config(
        "ppo", "1d-static-sin", **{**TINY, "total_steps": 5 * 32 * 16}, ent_coef=0.02, ent_coef_end=0.0
    )
    ppo = PPO(config)
    coefs = [float(ppo.ent_coef(u)) for u in range(config.num_updates)]
    np.testing.assert_allclose(coefs, [0.02, 0.015, 0.01, 0.005, 0.0], atol=1e-7)
    constant = PPO(make_config("ppo", "1d-static-sin", **TINY, ent_coef=0.02, ent_coef_end=0.02))
    assert (
        float(constant.ent_coef(0)) == float(constant.ent_coef(constant.config.num_updates - 1)) == pytest.approx(0.02)
    )


def test_config_rejects_unknown_task_and_algorithm():
    with pytest.raises(ValueError, match="unknown task 'nope'; allowed: 1d-static-sin"):
        make_config("ppo", "nope")
    with pytest.raises(ValueError, match="unknown algorithm 'a2c'; allowed: ppo"):
        make_config("a2c", "1d-static-sin")


def test_config_json_round_trip_and_tuned_defaults():
    config = make_config("ppo", "2d-static-dense", recurrent=True, seeds=3)
    assert config_from_json(config.to_json()) == config
    assert config.hidden_size != PPOConfig().hidden_size or config.num_envs != PPOConfig().num_envs

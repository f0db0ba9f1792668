"""Privileged training signals (SPEC §12): `env.privileged` on hand-made states, the auxiliary
losses by hand, the stride curriculum, the honest greedy policy (it reads observations only),
PPO and DRQN unchanged when every new signal is off, tiny runs, compile-once, the driver with two
seeds, and resume."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.research.drqn_aux import map_loss, move_loss, move_targets, position_loss, stride_curriculum
from agents.training.registry import build_algorithm, config_class, make_config
from snac_jax.env import draw_stride
from snac_jax.evaluation import run_episodes
from snac_jax.tasks import TASKS, make

PPO_TINY = dict(
    total_steps=2 * 16 * 8,
    num_envs=16,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=1,
    hidden_size=16,
    rnn_size=16,
    recurrent=True,
)
DRQN_TINY = dict(
    total_steps=4 * 8 * 8,
    num_envs=8,
    rollout_steps=8,
    batch_size=4,
    hidden_size=16,
    lstm_size=16,
    burn_in=2,
    sequence_length=4,
    learning_starts=0,
    buffer_size=8 * 40,
)
PQN_TINY = PPO_TINY  # PQN's rollout and minibatch options have PPO's names
TINY = {"ppo-privileged": PPO_TINY, "drqn-aux": DRQN_TINY, "pqn-aux": PQN_TINY, "pqn-belief": PQN_TINY}
ALL_SIGNALS = dict(position_coef=0.1, map_coef=0.1, move_coef=0.1, stride_curriculum=0.5)


def _run(agent, updates, seed=0):
    state = jax.jit(agent.init)(jax.random.key(seed))
    return jax.jit(lambda s: agent.train_chunk(s, agent.env_params, updates))(state)


def _same(a, b) -> bool:
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(leaves_a) == len(leaves_b) and all(np.array_equal(x, y) for x, y in zip(leaves_a, leaves_b))


# --- the environment's privileged state -------------------------------------------------------------


def test_privileged_state_of_hand_made_states():
    env, params = make("2d-static-dense")
    _, state = env.reset(jax.random.key(0), params)
    (pr, pc) = env.config.pad
    grid = state.grid.at[pr + 4, pc + 7].set(1).at[pr + 19, pc + 0].set(1)
    state = state.replace(grid=grid, position=jnp.array([4, 6], jnp.int32))
    privileged = env.privileged(state, params)
    built = np.zeros((20, 20), np.int8)
    built[4, 7] = built[19, 0] = 1
    np.testing.assert_array_equal(privileged.position, [4, 6])
    np.testing.assert_array_equal(privileged.built, built)
    np.testing.assert_array_equal(privileged.design, params.designs[0])
    assert not bool(privileged.stuck)

    # 3D with the obstacle rule: bricks on all four neighbours leave the robot stuck.
    env, params = make("3d-static-dense")
    _, state = env.reset(jax.random.key(0), params)
    (pr, pc), (r, c) = env.config.pad, (5, 5)
    grid = state.grid
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        grid = grid.at[pr + r + dr, pc + c + dc].set(2)
    free = state.replace(grid=grid.at[pr + r + 1, pc + c].set(0), position=jnp.array([r, c], jnp.int32))
    stuck = free.replace(grid=grid)
    assert bool(env.privileged(stuck, params).stuck) and not bool(env.privileged(free, params).stuck)
    assert int(env.privileged(stuck, params).built.sum()) == 8
    # Batched as `step` is; a 1D position is (0, column).
    env, params = make("1d-static-sin")
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(1), 3), params)
    batch = jax.vmap(env.privileged, in_axes=(0, None))(states, params)
    assert batch.position.shape == (3, 2) and batch.built.shape == (3, 1, 30) and batch.stuck.shape == (3,)


# --- the auxiliary losses by hand ---------------------------------------------------------------------


def test_position_loss_is_the_row_and_column_cross_entropy():
    # Plan 2 x 3; logits [rows | cols]; weights drop the second step.
    logits = jnp.array([[0.0, math.log(3.0), 0.0, 0.0, math.log(2.0)], [9.0, 0.0, 0.0, 9.0, 0.0]])
    position = jnp.array([[1, 2], [0, 0]])
    got = position_loss(logits, position, (2, 3), jnp.array([1.0, 0.0]))
    # Row 1 has probability 3/4, column 2 has 2/4.
    assert float(got) == pytest.approx(-math.log(3 / 4) - math.log(2 / 4), rel=1e-6)
    # 1D: one row, whose term is 0; uniform over 30 columns.
    assert float(position_loss(jnp.zeros((1, 31)), jnp.array([[0, 7]]), (1, 30), jnp.ones(1))) == pytest.approx(
        math.log(30)
    )


def test_map_loss_is_the_mean_squared_error_of_scaled_heights():
    built = jnp.array([[[0, 2], [4, 0]]])  # one step, plan 2 x 2, heights scaled by 4
    prediction = jnp.array([[0.5, 0.5, 1.0, 0.0]])
    expected = (0.5**2 + 0.0**2 + 0.0**2 + 0.0**2) / 4
    assert float(map_loss(prediction, built, 4.0, jnp.ones(1))) == pytest.approx(expected)


def test_move_targets_and_loss():
    # 1D actions: 0 left, 1 right, 2 drop. Steps: right by 3, drop, right by 1 (clipped at the wall),
    # then a new episode starts at step 4.
    position = jnp.array([[0, 5], [0, 8], [0, 8], [0, 9], [0, 0]])
    action = jnp.array([1, 2, 1, 0, 1])
    reset = jnp.array([True, False, False, False, True])
    is_move = jnp.array([True, True, False])
    cells, valid = move_targets(position, action, reset, is_move)
    np.testing.assert_array_equal(cells, [0, 3, 0, 1, 9])
    np.testing.assert_array_equal(valid, [False, True, False, True, False])
    # Only steps 1 (3 cells) and 3 (1 cell) count.
    logits = jnp.tile(jnp.array([0.0, 0.0, 0.0, math.log(5.0)]), (5, 1))  # P(3) = 5/8, others 1/8
    got = move_loss(logits, cells, valid, jnp.ones(5))
    assert float(got) == pytest.approx((-math.log(5 / 8) - math.log(1 / 8)) / 2, rel=1e-6)


def test_stride_curriculum_goes_from_no_noise_to_the_tasks():
    _, params = make("1d-static-sin")
    probs = [np.asarray(stride_curriculum(params, jnp.int32(u), 10, 0.4).stride_probs) for u in (0, 2, 4, 9)]
    third = 1 / 3
    np.testing.assert_allclose(probs[0], [1, 0, 0])
    np.testing.assert_allclose(probs[1], [0.5 + 0.5 * third, 0.5 * third, 0.5 * third], rtol=1e-6)
    np.testing.assert_allclose(probs[2], [third] * 3, rtol=1e-6)
    np.testing.assert_allclose(probs[3], [third] * 3, rtol=1e-6)
    words = jax.random.bits(jax.random.key(0), (1000,), jnp.uint32)
    assert set(np.asarray(jax.vmap(draw_stride, in_axes=(0, None))(words, jnp.asarray(probs[0]))).tolist()) == {1}


# --- learners -------------------------------------------------------------------------------------------


def _poison(params, names):
    """`params` with every weight of the named top-level modules set to NaN, to show which ones acting reads."""
    return {
        "params": {
            k: jax.tree.map(lambda x: jnp.full_like(x, jnp.nan), v) if k in names else v
            for k, v in params["params"].items()
        }
    }


@pytest.mark.slow
def test_the_greedy_policy_reads_observations_only():
    agent = build_algorithm(make_config("ppo-privileged", "2d-dynamic-sparse", **PPO_TINY, map_coef=0.1, move_coef=0.1))
    params = jax.jit(agent.init)(jax.random.key(0)).params
    policy = agent.policy(params)
    policy_state = policy.init(jax.random.key(1), agent.env_params.designs[0])
    obs, _ = agent.env.reset(jax.random.key(2), agent.env_params)
    key = jax.random.key(3)

    assert {x.shape for x in jax.tree.leaves(policy_state)} <= {(16,), (), (obs.shape[0],)}
    # The critic and the auxiliary heads are not on the acting path: NaN weights there change nothing.
    names = set(params["params"])
    assert {"PrivilegedEncoder_0", "auxiliary_heads"} <= names

    critic = {"PrivilegedEncoder_0", "auxiliary_heads", "Dense_2", "Dense_3"}  # Dense_0/1: the actor's head
    action, after = policy.act(params, policy_state, obs, key)
    action_poisoned, after_poisoned = policy.act(_poison(params, critic), policy_state, obs, key)
    assert int(action) == int(action_poisoned) and _same(after, after_poisoned)
    _, after_poisoned_memory = policy.act(_poison(params, {"ScannedRNN_0"}), policy_state, obs, key)
    assert np.all(np.isnan(after_poisoned_memory["carry"]))  # poison where acting does read shows


@pytest.mark.slow
def test_pqn_aux_heads_learn_from_the_true_position_and_are_not_on_the_acting_path():
    agent = build_algorithm(make_config("pqn-aux", "2d-static-dense", **PQN_TINY, max_steps=5))
    state = jax.jit(agent.init)(jax.random.key(0))
    _, batch, _ = jax.jit(agent.rollout)(state, agent.env_params)
    # The targets are where each observation was made: the first step's, the worlds' positions before it.
    assert batch.auxiliary["position"].shape == (8, 16, 2) and batch.auxiliary["built"] is None
    assert _same(batch.auxiliary["position"][0], state.worlds.env_state.position)
    # ... and after an episode ends inside the rollout (max_steps 5), the new episode's first
    # observation is scored against the reset position (the plan origin), not the last one's.
    position, reset = np.asarray(batch.auxiliary["position"]), np.asarray(batch.reset)
    later = reset[1:].any(axis=1).nonzero()[0] + 1
    assert later.size, "no episode ended inside the rollout"
    for t in later:
        assert (position[t][reset[t]] == 0).all()
        assert (position[t - 1][reset[t]] != 0).any()  # where the ended episodes were: the check bites
    policy = agent.policy(state.params)
    assert policy.name == "pqn-aux-recurrent"  # what a rendered episode's title says
    policy_state = policy.init(jax.random.key(2), agent.env_params.designs[0])
    obs, _ = agent.env.reset(jax.random.key(3), agent.env_params)
    poisoned = _poison(state.params, {"auxiliary_heads"})
    assert "auxiliary_heads" in state.params["params"]
    action, after = policy.act(state.params, policy_state, obs, jax.random.key(4))
    action_poisoned, after_poisoned = policy.act(poisoned, policy_state, obs, jax.random.key(4))
    assert int(action) == int(action_poisoned) and _same(after, after_poisoned)


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_with_every_signal_off_the_learners_are_ppo_drqn_and_pqn():
    """The hooks leave PPO, DRQN and PQN as they were: the new learners with the privileged critic off
    and every auxiliary weight 0 reproduce them exactly (truncations included: max_steps 5), and
    the evaluator scores their greedy policies alike."""
    task, off = "1d-static-sin", dict(position_coef=0.0, map_coef=0.0, move_coef=0.0)
    pairs = [
        ("ppo", "ppo-privileged", dict(PPO_TINY, max_steps=5), dict(privileged_critic=False, **off)),
        ("drqn", "drqn-aux", dict(DRQN_TINY, max_steps=5), off),
        ("pqn", "pqn-aux", dict(PQN_TINY, max_steps=5), off),
    ]
    for base, new, options, switches in pairs:
        agents = [
            build_algorithm(make_config(name, task, **options, **extra))
            for name, extra in ((base, {}), (new, switches))
        ]
        (state_a, metrics_a), (state_b, metrics_b) = (_run(agent, 2) for agent in agents)
        assert set(metrics_a) == set(metrics_b) and _same(metrics_a, metrics_b), (base, new)
        assert _same(state_a.params, state_b.params), (base, new)
        if base == "ppo":
            env, params = make(task, max_steps=20)
            scores = [
                run_episodes(env, params, a.policy(s.params), jax.random.key(4), np.zeros(4, np.int32)).iou
                for a, s in zip(agents, (state_a, state_b))
            ]
            np.testing.assert_array_equal(*scores)


@pytest.mark.slow  # a whole driver run (minutes on 2 cores): `pytest -m slow`
@pytest.mark.parametrize(
    "algorithm,task",
    [
        ("ppo-privileged", "2d-dynamic-sparse"),
        ("ppo-privileged", "3d-static-dense"),
        ("drqn-aux", "1d-static-sin"),
        ("pqn-aux", "2d-static-sparse"),
        ("pqn-belief", "2d-dynamic-dense"),
        ("pqn-belief", "3d-static-dense"),
    ],
)
def test_tiny_runs_with_every_signal_are_finite_and_compile_once(algorithm, task):
    options = TINY[algorithm]
    agent = build_algorithm(make_config(algorithm, task, **options, **ALL_SIGNALS, max_steps=6))
    traces = []
    update = agent.update
    agent.update = lambda state, env_params: (traces.append(1), update(state, env_params))[1]
    chunk = jax.jit(lambda s, p: agent.train_chunk(s, p, 2))
    state = jax.jit(agent.init)(jax.random.key(0))
    state, first = chunk(state, agent.env_params)
    state, second = chunk(state, agent.env_params)
    assert len(traces) == 1 and chunk._cache_size() == 1
    for name in ("loss", "position_loss", "map_loss", "move_loss"):
        assert np.all(np.isfinite(first[name])) and np.all(np.isfinite(second[name])), name
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))
    # The curriculum reached the task's strides after half of the run's updates.
    np.testing.assert_allclose(second["p_stride_1"][-1], 1 / 3, rtol=1e-6)
    assert float(first["p_stride_1"][0]) == 1.0


@pytest.mark.slow  # a whole driver run (minutes on 2 cores): `pytest -m slow`
def test_two_seeds_through_the_driver_and_the_checkpoint_evaluates(tmp_path):
    from agents.training.driver import read_metrics, train
    from agents.training.trained import checkpoint_policy

    config = make_config(
        "ppo-privileged",
        "1d-static-sin",
        **{**PPO_TINY, "total_steps": 2 * 16 * 8},
        chunks=2,
        seeds=2,
        move_coef=0.1,
        max_steps=6,
    )
    _, state = train(config, tmp_path / "run", progress=False)
    assert int(state.update[0]) == int(state.update[1]) == config.num_updates
    lines = read_metrics(tmp_path / "run")
    assert len(lines) == 2 and len(lines[-1]["position_loss"]) == 2 and len(lines[-1]["move_loss"]) == 2
    first = jax.tree.leaves(state.params)[0]
    assert not np.array_equal(first[0], first[1])
    env, params = make("1d-static-sin", max_steps=12)
    policy = checkpoint_policy(env, tmp_path / "run", seed_index=1)
    episodes = run_episodes(env, params, policy, jax.random.key(0), np.zeros(2, np.int32))
    assert np.all((episodes.iou >= 0) & (episodes.iou <= 1))


@pytest.mark.slow  # three driver runs of each learner: over 20 s on a 2-core CPU
@pytest.mark.parametrize("algorithm", ["ppo-privileged", "drqn-aux", "pqn-aux", "pqn-belief"])
def test_resume_equals_the_uninterrupted_run(algorithm, tmp_path):
    from agents.training.checkpoint import to_storable
    from agents.training.driver import train

    options = TINY[algorithm]
    config = make_config(algorithm, "1d-static-sin", **options, **ALL_SIGNALS, chunks=2, max_steps=6)
    _, straight = train(config, tmp_path / "straight", progress=False)
    train(config, tmp_path / "cut", progress=False, stop_after_chunks=1)
    _, resumed = train(config, tmp_path / "cut", resume=True, progress=False)
    assert _same(to_storable(straight), to_storable(resumed))


# --- configuration --------------------------------------------------------------------------------------


# pqn-aux and pqn-belief are PQN-RNN (`pqn --recurrent`), which plain pqn is not on every task (agents/tuned/pqn.toml)
VARIANTS = [
    ("ppo-privileged", "ppo", {}),
    ("drqn-aux", "drqn", {}),
    ("pqn-aux", "pqn", {"recurrent": True}),
    ("pqn-belief", "pqn", {"recurrent": True}),
]


@pytest.mark.parametrize("algorithm,base,base_options", VARIANTS)
@pytest.mark.parametrize("task", TASKS)
def test_a_variant_resolves_to_its_base_learner_plus_its_signals(algorithm, base, base_options, task):
    """On every task a variant's config is its base learner's tuned config with the training
    signals added, so a comparison with the base is of the signals alone; where the variant's
    own tuned file has an entry for the task (`agents.training.registry.tuned_files`), the base's config
    with that entry's settings."""
    from agents.training.registry import TUNED_DIR

    extra = {"algorithm"} | {f.name for f in dataclasses.fields(config_class(algorithm))} - {
        f.name for f in dataclasses.fields(config_class(base))
    }
    own_file = TUNED_DIR / f"{algorithm}.toml"  # read here, not through the registry's layering under test
    own = tomllib.loads(own_file.read_text()).get(task, {}) if own_file.is_file() else {}
    base_options = {**base_options, **{k: v for k, v in own.items() if k != "result" and k not in extra}}
    variant, plain = make_config(algorithm, task).to_json(), make_config(base, task, **base_options).to_json()
    assert extra - {"algorithm"} and set(variant) - set(plain) == extra - {"algorithm"}
    assert {k: v for k, v in variant.items() if k not in extra} == {k: v for k, v in plain.items() if k not in extra}


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(position_coef=-0.1), r"position_coef must be a number >= 0"),
        (dict(stride_curriculum=1.5), r"stride_curriculum must be a number in \[0, 1\]"),
        (dict(privileged_critic=1), "privileged_critic must be True or False"),
    ],
)
def test_config_errors_are_clear(options, message):
    with pytest.raises(ValueError, match=message):
        make_config("ppo-privileged", "1d-static-sin", **options)


def test_pqn_aux_needs_its_recurrent_core():
    with pytest.raises(ValueError, match="pqn-aux needs recurrent=True: its auxiliary heads read the GRU's state"):
        make_config("pqn-aux", "2d-static-dense", recurrent=False)

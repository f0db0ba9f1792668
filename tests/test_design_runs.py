"""A dynamic task's design read once per run of one design (`agents.common.networks.
encode_design_runs`): by hand, against the per-step encoding inside every learner across episode
boundaries, and the bound it relies on (`agents.common.inputs.episode_min_steps`) against the
environment."""

from __future__ import annotations

import dataclasses
import functools

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from agents.common import networks
from agents.common.inputs import ObsLayout, episode_min_steps
from agents.training.registry import ALGORITHMS, build_algorithm, config_class, make_config
from snac_jax import make


def _designs(runs_per_column: list[list[tuple[int, int]]]) -> np.ndarray:
    """`(T, B, 1, 2)` designs from each column's runs `(value, length)`."""
    columns = [np.concatenate([np.full(length, value) for value, length in runs]) for runs in runs_per_column]
    values = np.stack(columns, axis=1).astype(np.float32)  # (T, B)
    return np.stack([values, 2 * values], axis=-1)[:, :, None, :]


def test_each_run_is_encoded_once_and_every_step_reads_its_runs_features():
    designs = _designs([[(1, 2), (5, 3), (1, 1)], [(7, 6)]])  # column 0: three runs; column 1: one
    seen = []

    def encode(d):
        seen.append(d.shape)
        return jnp.stack([d.sum((-1, -2)), d.max((-1, -2))], axis=-1)

    out = jax.jit(networks.encode_design_runs, static_argnums=(0, 2))(encode, jnp.asarray(designs), 3)
    assert seen == [(3, 2, 1, 2)]  # three designs a column, not six (traced once: one program, not one per op)
    expected = np.stack([designs.sum((-1, -2)), designs.max((-1, -2))], axis=-1)
    np.testing.assert_array_equal(np.asarray(out), expected)
    # By hand: column 0 reads runs 1, 5, 1 (sum 3 * value), column 1 its one design throughout.
    assert np.asarray(out)[:, 0, 0].tolist() == [3, 3, 15, 15, 15, 3]
    assert np.asarray(out)[:, 1, 0].tolist() == [21] * 6


def test_a_bound_that_is_too_small_reads_nan_rather_than_another_runs_design():
    designs = jnp.asarray(_designs([[(1, 2), (5, 3), (1, 1)], [(7, 6)]]))
    encode = lambda d: d.sum((-1, -2))[..., None]
    out = np.asarray(jax.jit(networks.encode_design_runs, static_argnums=(0, 2))(encode, designs, 2))
    assert np.isnan(out[5, 0]).all() and np.isfinite(out[:5, 0]).all() and np.isfinite(out[:, 1]).all()


def test_the_gradient_through_the_runs_equals_the_per_step_gradient():
    designs = jnp.asarray(_designs([[(1, 2), (5, 3), (1, 1)], [(7, 4), (2, 2)]]))
    weights = jnp.arange(1.0, 13.0).reshape(6, 2)

    def loss(w, max_runs):
        encode = lambda d: jnp.tanh(d.reshape(d.shape[:2] + (2,)) @ w[:2]) * w[2:4]
        return (networks.encode_design_runs(encode, designs, max_runs) * weights[..., None]).sum()

    w = jnp.array([[0.3, -0.2], [0.1, 0.4], [1.0, 2.0], [0.5, -1.0]])
    grad = jax.jit(jax.grad(loss), static_argnums=1)  # one program per bound, not one per operation
    np.testing.assert_allclose(grad(w, 3), grad(w, 6), rtol=1e-5)  # summed in another order


@pytest.mark.parametrize(
    "task,overrides,expected",
    [
        ("2d-dynamic-dense", {}, 51),  # the bank's smallest design has 51 cells: its budget is below 600 steps
        ("1d-dynamic", {"max_steps": 7}, 7),  # the step limit
        ("3d-dynamic-sparse", {}, 3),  # the obstacle rule: walled in after two drops
        ("2d-dynamic-sparse", {"obstacles": True}, 3),
    ],
)
def test_episode_min_steps_of_a_task(task, overrides, expected):
    env, params = make(task, **overrides)
    assert episode_min_steps(env, params) == expected


def test_a_teams_bound_divides_the_budget_among_its_robots():
    env, params = make("2d-dynamic-dense")
    assert [episode_min_steps(env, params, robots) for robots in (1, 2, 4)] == [51, 26, 13]


@pytest.mark.slow
@pytest.mark.parametrize("robots", [1, 4])
def test_robots_that_drop_at_every_step_end_no_episode_sooner_than_the_bound(robots):
    """Every robot dropping on its own cell each step spends the team's budget fastest (2D: the
    drop action, 4); the first episode lasts at least `episode_min_steps`, and with the bank's
    smallest budget exactly that many steps."""
    from snac_jax import multi

    env = multi.make("2d-dynamic-sparse", num_robots=robots)
    params = env.default_params
    bound = episode_min_steps(env.single, params, robots)
    budgets = np.asarray(params.design_max_bricks)
    pick = lambda x: x[np.argmin(budgets)][None]  # the bank's design with the smallest budget, alone
    smallest = params.replace(
        designs=pick(params.designs),
        design_max_bricks=pick(params.design_max_bricks),
        design_volume=pick(params.design_volume),
    )
    step_env = jax.jit(env.step_env)  # one program a bank, not one per operation
    for p in (params, smallest):
        _, state = env.reset(jax.random.key(0), p)
        actions = {agent: 4 for agent in env.agents}
        for step in range(1, 2 * bound + 2):
            _, state, _, dones, _ = step_env(jax.random.key(step), state, actions, p)
            if bool(dones["__all__"]):
                break
        assert step >= bound
    assert step == bound  # the smallest budget: the bound is reached


def test_a_design_change_is_a_second_run_inside_the_bound():
    env, params = make("2d-dynamic-sparse", design_change=(2, 3), max_steps=6)
    layout = ObsLayout.from_env(env, params)
    assert layout.designs_per_episode == 2 and layout.max_design_runs(12) == 2 * (1 + 2)
    _, state = env.reset(jax.random.key(0), params)
    obs, designs = None, []
    for step in range(12):
        obs, state, *_ = env.step(jax.random.key(step), state, 0, params)
        designs.append(np.asarray(obs[layout.env.design]))
    runs = 1 + sum(not np.array_equal(a, b) for a, b in zip(designs, designs[1:]))
    assert 2 < runs <= layout.max_design_runs(12)


@pytest.mark.slow
def test_the_obstacle_bound_is_reached_by_a_robot_that_walls_itself_in():
    """From the corner start, drops on c+1 and r+1 (actions 5 and 6) leave no free neighbour; the
    third action ends the episode: 3 steps, the bound `episode_min_steps` gives in 3D."""
    env, params = make("3d-dynamic-dense")
    _, state = env.reset(jax.random.key(0), params)
    ended = []
    for action in (5, 6, 0):
        _, state, _, terminated, truncated, _ = env.step(jax.random.key(1), state, action, params)
        ended.append(bool(terminated | truncated))
    assert ended == [False, False, True]
    assert episode_min_steps(env, params) == 3


@functools.partial(jax.jit, static_argnames=("env", "worlds", "steps"))
def _random_rollout(env, params, seed, worlds, steps):
    """Each step's observations of `worlds` worlds taking random actions, with auto-reset. Jitted
    with the params an argument (the step limit is in them): one program a task, whatever the
    limit and seed, not one per example."""
    keys = jax.random.split(jax.random.key(seed), worlds)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

    def step(carry, key):
        obs, state = carry
        action_key, step_key = jax.random.split(key)
        actions = jax.random.randint(action_key, (worlds,), 0, env.num_actions)
        obs2, state2, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(step_key, worlds), state, actions, params
        )
        return (obs2, state2), obs

    return jax.lax.scan(step, (obs, state), jax.random.split(jax.random.key(seed + 1), steps))[1]


@pytest.mark.slow
@settings(max_examples=8, deadline=None)
@given(
    task=st.sampled_from(["1d-dynamic", "2d-dynamic-sparse", "3d-dynamic-dense"]),
    max_steps=st.integers(1, 9),
    seed=st.integers(0, 2**16),
)
def test_random_rollouts_never_hold_more_design_runs_than_the_bound(task, max_steps, seed):
    env, params = make(task, max_steps=max_steps)
    layout = ObsLayout.from_env(env, params)
    worlds, steps = 16, 24
    observed = _random_rollout(env, params, seed, worlds, steps)
    design = np.asarray(observed[..., layout.env.design])
    runs = 1 + (design[1:] != design[:-1]).any(-1).sum(0)
    for window in (2, 5, steps):
        starts = range(0, steps - window + 1)
        most = max(1 + (design[s + 1 : s + window] != design[s : s + window - 1]).any(-1).sum(0).max() for s in starts)
        assert most <= layout.max_design_runs(window)
    assert runs.max() <= layout.max_design_runs(steps)


# Every learner's tiny settings: the union of the keys the learners' tests pin; each takes those of
# its config's fields.
TINY = dict(
    num_envs=4,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=1,
    hidden_size=8,
    rnn_size=8,
    batch_size=8,
    learning_starts=0,
    gradient_steps=1,
    lstm_size=8,
    burn_in=2,
    sequence_length=6,
    max_steps=5,  # several episodes inside every rollout and sequence
)


def _tiny_config(algorithm: str, task: str):
    fields = {f.name for f in dataclasses.fields(config_class(algorithm))}
    return make_config(algorithm, task, **{k: v for k, v in TINY.items() if k in fields})


def _chunk_params(algorithm_name: str, task: str):
    agent = build_algorithm(_tiny_config(algorithm_name, task))
    state = jax.jit(agent.init)(jax.random.key(3))
    state, _ = jax.jit(lambda s: agent.train_chunk(s, agent.env_params, 2))(state)
    return state.params


def _reads_the_design(params) -> bool:
    return any("DesignEncoder" in jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_leaves_with_path(params))


# PPO in the default run; every learner in the slow one (each compiles two tiny trainings).
LEARNERS = [pytest.param(a, marks=() if a == "ppo" else pytest.mark.slow) for a in sorted(ALGORITHMS)]


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", LEARNERS)
def test_each_learner_trains_the_same_with_the_design_read_once_per_run(algorithm, monkeypatch):
    """Two updates on episodes of 5 steps (several inside each rollout or sequence) train the same
    parameters, to float tolerance, with the design encoded once per run, by the CPU's loop
    (`encode_each_run`) and by the accelerators' bounded pass (`encode_design_runs`), as encoded
    at every step; the learners whose sequences are longer than one step encode fewer designs
    than steps."""
    task = "1d-dynamic"
    looped, bounded = [], []
    each_run, runs = networks.encode_each_run, networks.encode_design_runs

    def each_run_spy(apply, params, designs, chunk):
        looped.append(designs.shape[0])
        return each_run(apply, params, designs, chunk)

    def runs_spy(encode, designs, max_runs):
        bounded.append((designs.shape[0], max_runs))
        return runs(encode, designs, max_runs)

    refreshed = []
    refresh = networks.refresh_design_features

    def refresh_spy(encode, designs, seen, features):
        refreshed.append(designs.shape)
        return refresh(encode, designs, seen, features)

    monkeypatch.setattr(networks, "encode_each_run", each_run_spy)
    monkeypatch.setattr(networks, "encode_design_runs", runs_spy)
    monkeypatch.setattr(networks, "refresh_design_features", refresh_spy)
    monkeypatch.setattr(networks, "runs_in_a_loop", lambda: True)
    in_a_loop = _chunk_params(algorithm, task)
    monkeypatch.setattr(networks, "runs_in_a_loop", lambda: False)
    in_one_pass = _chunk_params(algorithm, task)
    engaged = any(max_runs < steps for steps, max_runs in bounded)
    monkeypatch.setattr(ObsLayout, "max_design_runs", lambda self, steps: steps)
    monkeypatch.setattr(networks, "refresh_design_features", lambda encode, designs, seen, features: encode(designs))
    every_step = _chunk_params(algorithm, task)
    for params in (in_a_loop, in_one_pass):
        for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(every_step)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)
    if not bounded:  # a network that reads the design otherwise (pqn-belief's expected window alone)
        assert not looped and not _reads_the_design(in_a_loop)
        return
    assert looped, "its sequences encode the design at every step on a CPU"
    assert engaged, bounded  # every learner trains on sequences (replayed windows too) longer than the bound
    # and acts with each world's design features kept between steps (`networks.apply_with_design_cache`)
    assert refreshed, "its rollout encodes every world's design at every step"


def test_the_loop_encodes_each_run_once_in_passes_of_its_chunk():
    """Column 0 holds three runs, column 1 one: four runs, two a pass, so two passes of two
    designs; every step reads its own run's features (by hand, as the bounded pass's test)."""
    designs = jnp.asarray(_designs([[(1, 2), (5, 3), (1, 1)], [(7, 6)]]))
    calls = []
    encode = _encode_counting(calls)
    out = jax.jit(networks.encode_each_run, static_argnums=(0, 3))(lambda _, d: encode(d), {}, designs, 2)
    assert calls == [2, 2]
    assert np.asarray(out)[:, 0, 0].tolist() == [3, 3, 15, 15, 15, 3]
    assert np.asarray(out)[:, 1, 0].tolist() == [21] * 6
    assert np.asarray(out)[:, 0, 1].tolist() == [2, 2, 10, 10, 10, 2]


STEPS, COLUMNS = 8, 4  # one shape for every example: one program per chunk, not one per example


@functools.partial(jax.jit, static_argnums=0)
def _loop_and_step(chunk, designs, weights, params):
    """Features and gradients (vmapped over a leading parameter axis, as over seeds) of the loop
    and of the per-step encoding."""

    def features(p, loop):
        if loop:
            return networks.encode_each_run(_tanh_apply, p, designs, chunk)
        flat = _tanh_apply(p, designs.reshape((-1,) + designs.shape[2:]))
        return flat.reshape(designs.shape[:2] + (2,))

    grads = [jax.vmap(jax.grad(lambda p: (features(p, loop) * weights).sum()))(params) for loop in (True, False)]
    first = jax.tree.map(lambda x: x[0], params)
    return [features(first, loop) for loop in (True, False)], grads


@pytest.mark.slow
@settings(max_examples=20, deadline=None)
@given(
    starts=st.lists(
        st.lists(st.booleans(), min_size=STEPS - 1, max_size=STEPS - 1), min_size=COLUMNS, max_size=COLUMNS
    ),
    chunk=st.sampled_from([1, 3, 16]),
)
def test_the_loop_is_exact_however_many_runs_with_the_per_step_gradient(starts, chunk):
    """Any runs (every step a run of its own included, far past any bound), a chunk of one run
    to more than all: the features are the per-step encoding's and the gradient the per-step
    gradient, also vmapped over two parameter sets as over seeds."""
    # each column's run index along its steps, its values distinct between columns and runs
    runs = np.cumsum(np.concatenate([np.ones((COLUMNS, 1), bool), np.array(starts)], axis=1), axis=1).T
    values = (runs + 10 * np.arange(COLUMNS)).astype(np.float32)  # (T, B)
    designs = jnp.asarray(np.stack([values, 2 * values], axis=-1)[:, :, None, :])
    weights = jnp.asarray(np.random.default_rng(int(runs.sum())).normal(size=(STEPS, COLUMNS, 2)), jnp.float32)
    params = {"w": jnp.array([[0.3, -0.2], [0.1, 0.4]]), "s": jnp.array([1.0, 2.0])}
    both = jax.tree.map(lambda x: jnp.stack([x, -1.5 * x]), params)
    (looped, per_step), (loop_grads, step_grads) = _loop_and_step(chunk, designs, weights, both)
    np.testing.assert_allclose(np.asarray(looped), np.asarray(per_step), rtol=1e-6)
    for a, b in zip(jax.tree.leaves(loop_grads), jax.tree.leaves(step_grads)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)


def _tanh_apply(params, designs):
    return jnp.tanh(designs.reshape(designs.shape[0], 2) @ params["w"]) * params["s"]


def _encode_counting(calls):
    def encode(d):  # counts its executions (a loop body is traced once)
        jax.debug.callback(lambda: calls.append(d.shape[0]))
        return jnp.stack([d.sum((-1, -2)), d.max((-1, -2))], axis=-1)

    return encode


def test_the_cache_encodes_only_the_worlds_whose_design_changed():
    """40 worlds, a chunk of 3 a pass on the CPU: a first step encodes every world (14 passes), a
    step where worlds 5 and 31 start an episode one pass, a step without a change none; the
    features are always the designs' own."""
    assert networks.design_refresh_chunk(40) == 3
    designs = jnp.arange(40 * 6, dtype=jnp.float32).reshape(40, 2, 3)
    calls = []
    encode = _encode_counting(calls)
    expected = lambda d: np.stack([np.asarray(d).sum((-1, -2)), np.asarray(d).max((-1, -2))], axis=-1)
    refresh = jax.jit(networks.refresh_design_features, static_argnums=0)  # one program, not one per op
    features = refresh(encode, designs, jnp.full_like(designs, jnp.nan), jnp.zeros((40, 2)))
    np.testing.assert_array_equal(np.asarray(features), expected(designs))
    assert calls == [3] * 14
    calls.clear()
    new = designs.at[jnp.array([5, 31])].add(1000.0)
    refreshed = refresh(encode, new, designs, features)
    np.testing.assert_array_equal(np.asarray(refreshed), expected(new))
    assert calls == [3]
    calls.clear()
    assert np.array_equal(np.asarray(refresh(encode, new, new, refreshed)), expected(new))
    assert calls == []


@pytest.mark.slow
def test_a_rollouts_first_cache_holds_every_worlds_features_from_one_pass(monkeypatch):
    """`first_design_cache` encodes the first step's designs in one pass, and acting from it gives
    the outputs of the network that encodes every design; the step after it re-encodes no world
    (the refresh finds none changed), and a world whose design changed is refreshed."""
    env, params = make("2d-dynamic-sparse")
    layout = ObsLayout.from_env(env, params)
    network = networks.QNetwork(layout=layout, num_actions=env.num_actions, hidden_size=8)
    obs, _ = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), 6), params)
    frames = obs[None, :, None, :].astype(jnp.float32)  # (T=1, B=6, k=1, O)
    carry, resets = network.initial_carry(6), jnp.ones((1, 6), bool)
    variables = jax.jit(network.init)(jax.random.key(1), carry, frames, resets)
    changed = []
    refresh = networks.refresh_design_features

    def count_changed(designs, seen):  # run at each execution of the (jitted) refresh
        changed.append(int(np.any(np.asarray(designs != seen).reshape(len(designs), -1), axis=1).sum()))

    monkeypatch.setattr(
        networks,
        "refresh_design_features",
        lambda encode, designs, seen, features: (
            jax.debug.callback(count_changed, designs, seen),
            refresh(encode, designs, seen, features),
        )[1],
    )
    # Jitted, each one program rather than one per operation.
    apply = jax.jit(network.apply)
    first_cache = jax.jit(lambda *inputs: networks.first_design_cache(network, *inputs))
    with_cache = jax.jit(lambda *inputs: networks.apply_with_design_cache(network, *inputs))
    cache = first_cache(variables, carry, frames, resets)
    assert changed == []  # one pass, not the refresh's chunks
    direct = apply(variables, carry, frames, resets)[1]
    cached, cache = with_cache(variables, cache, carry, frames, resets)
    np.testing.assert_allclose(np.asarray(cached[1]), np.asarray(direct), rtol=1e-5, atol=1e-6)
    assert changed == [0]
    design = layout.env.design
    other = frames.at[0, 2, 0, design].set(1.0 - frames[0, 2, 0, design])
    cached, _ = with_cache(variables, cache, carry, other, resets)
    np.testing.assert_allclose(
        np.asarray(cached[1]), np.asarray(apply(variables, carry, other, resets)[1]), rtol=1e-5, atol=1e-6
    )
    assert changed == [0, 1]


@pytest.mark.slow
@pytest.mark.parametrize("way", ["loop", "bounded pass", "acting"])
def test_the_first_layers_design_share_once_per_run_equals_the_layer_over_every_step(way, monkeypatch):
    """`ObservationEncoder` computes its first layer's product with the design features once per
    run (`design_features` given the layer's rows for them) over a sequence, by the loop and by
    the bounded pass, and once per episode when acting with the cache: its outputs (and over a
    sequence its gradients) are those of the same layer over every step's concatenated inputs, to
    float tolerance, on random episodes of 3 to 4 steps."""
    env, params = make("2d-dynamic-sparse", max_steps=4)
    layout = ObsLayout.from_env(env, params)
    obs = _random_rollout(env, params, 7, 3, 12)  # (T, B, O)
    network = networks.ObservationEncoder(layout, hidden_size=8, layer_norm=True)
    variables = jax.jit(network.init)(jax.random.key(0), obs)
    kernels = []
    features = networks.ObservationEncoder.design_features

    def features_spy(self, design, kernel=None):
        kernels.append(kernel)
        return features(self, design, kernel)

    monkeypatch.setattr(networks.ObservationEncoder, "design_features", features_spy)
    monkeypatch.setattr(networks, "runs_in_a_loop", lambda: way == "loop")

    def outputs(variables):  # traced anew by each jit below: a new lambda each time
        if way == "acting":  # two steps, the second refreshing the worlds whose episode changed
            cache = networks.first_design_cache(network, variables, obs[:1])
            first, cache = networks.apply_with_design_cache(network, variables, cache, obs[:1])
            return [first, networks.apply_with_design_cache(network, variables, cache, obs[1:2])[0]]
        grad = jax.grad(lambda v: jnp.sin(network.apply(v, obs)).sum())(variables)
        return [network.apply(variables, obs), grad]

    once_per_run = jax.jit(lambda v: outputs(v))(variables)
    assert kernels and all(k is not None for k in kernels)  # the split layer, every call
    monkeypatch.setattr(networks.ObservationEncoder, "_design_once_per_run", lambda self, design: False)
    calls = len(kernels)
    every_step = jax.jit(lambda v: outputs(v) if way != "acting" else [network.apply(v, obs[:2])])(variables)
    assert kernels[calls:] and all(k is None for k in kernels[calls:])
    if way == "acting":
        once_per_run = [jnp.concatenate(once_per_run)]
    for a, b in zip(jax.tree.leaves(once_per_run), jax.tree.leaves(every_step)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)

"""Rainbow: the C51 projection, n-step returns and the loss with its priorities by hand, prioritised
replay's importance weights for hand-set priorities, the noisy layer, tiny runs (finite losses,
compiled once, two seeds through the driver), the noise-free greedy policy, resume, the CLI, and the
paper's settings."""

from __future__ import annotations

import dataclasses

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.noisy import NoisyDense
from agents.common.offpolicy import Step
from agents.common.targets import categorical_projection, n_step_returns
from agents.learners.rainbow import Rainbow, RainbowConfig, cross_entropy_and_kl, importance_weights
from agents.training.registry import build_algorithm, make_config
from tests.helpers import check_each_seed_evaluates_from_the_checkpoint

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
    atoms=11,
    total_steps=4 * 64,
    buffer_size=8 * 40,
    max_steps=14,
)


def _agent(task="1d-static-sin", **options) -> Rainbow:
    return build_algorithm(make_config("rainbow", task, **{**TINY, **options}))


# --- pure pieces -------------------------------------------------------------------------------------


def test_categorical_projection_matches_hand_computation():
    support = jnp.arange(5.0)  # atoms 0, 1, 2, 3, 4: V_min = 0, V_max = 4, spacing 1
    p = jnp.array([0.1, 0.2, 0.3, 0.2, 0.2])
    cases = [  # (reward sum, discount, expected projection)
        # 0.5 + 0.5 z = 0.5, 1, 1.5, 2, 2.5: the mass 0.1 at 0.5 splits 0.05 / 0.05 onto atoms 0 and 1,
        # 0.2 lands on 1, 0.3 at 1.5 splits 0.15 / 0.15 onto 1 and 2, 0.2 lands on 2, 0.2 at 2.5
        # splits 0.1 / 0.1 onto 2 and 3: [0.05, 0.05 + 0.2 + 0.15, 0.15 + 0.2 + 0.1, 0.1, 0].
        (0.5, 0.5, [0.05, 0.4, 0.45, 0.1, 0.0]),
        # Beyond V_max: 1.5 + z = 1.5, 2.5, 3.5, 4.5, 5.5, clipped to 1.5, 2.5, 3.5, 4, 4:
        # 0.05 / 0.05 onto 1, 2; 0.1 / 0.1 onto 2, 3; 0.15 / 0.15 onto 3, 4; 0.2 + 0.2 onto 4.
        (1.5, 1.0, [0.0, 0.05, 0.15, 0.25, 0.55]),
        # Discounted and beyond V_max: 3 + 0.5 z = 3, 3.5, 4, 4.5, 5, clipped to 3, 3.5, 4, 4, 4:
        # 0.1 onto 3; 0.2 at 3.5 splits 0.1 / 0.1 onto 3 and 4; 0.3 + 0.2 + 0.2 onto 4.
        (3.0, 0.5, [0.0, 0.0, 0.0, 0.2, 0.8]),
        # Below V_min: -2.5 + z = -2.5, -1.5, -0.5, 0.5, 1.5, clipped to 0, 0, 0, 0.5, 1.5:
        # 0.1 + 0.2 + 0.3 onto 0; 0.1 / 0.1 onto 0, 1; 0.1 / 0.1 onto 1, 2.
        (-2.5, 1.0, [0.7, 0.2, 0.1, 0.0, 0.0]),
        # Terminal (discount 0): everything at the reward 2.7, split 0.3 / 0.7 onto atoms 2 and 3.
        (2.7, 0.0, [0.0, 0.0, 0.3, 0.7, 0.0]),
        # Terminal with the reward beyond V_max: everything on the last atom.
        (9.0, 0.0, [0.0, 0.0, 0.0, 0.0, 1.0]),
    ]
    returns = jnp.array([c[0] for c in cases])
    discounts = jnp.array([c[1] for c in cases])
    # Jitted, here and below: one program (op by op, some twenty).
    projected = jax.jit(categorical_projection)(support, jnp.broadcast_to(p, (len(cases), 5)), returns, discounts)
    np.testing.assert_allclose(projected, [c[2] for c in cases], atol=1e-6)


def test_projection_onto_the_papers_support_keeps_mass_and_unclipped_means():
    support = np.linspace(-5.0, 35.0, 101, dtype=np.float32)
    probs = np.asarray(jax.jit(lambda key: jax.nn.softmax(jax.random.normal(key, (6, 101))))(jax.random.key(0)))
    returns = np.array([0.0, 1.0, -0.3, 2.2, 0.7, 0.1], np.float32)
    discounts = np.array([0.5, 0.6, 0.7, 0.4, 0.0, 0.3], np.float32)  # keeps r + d z inside [-5, 35]
    projected = np.asarray(jax.jit(categorical_projection)(support, probs, returns, discounts))
    np.testing.assert_allclose(projected.sum(-1), 1.0, rtol=1e-5)
    # Splitting each atom's mass linearly between its neighbours keeps the mean: r + d E[Z].
    np.testing.assert_allclose(projected @ support, returns + discounts * (probs @ support), rtol=1e-4, atol=1e-4)


def test_n_step_returns_stop_at_an_episode_end_inside_the_window():
    gamma = 0.5
    rewards = jnp.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0])[:, None]
    dones = jnp.array([False, True, False, False, False, False])[:, None]
    sums, discounts = n_step_returns(rewards, dones, gamma, n=3, length=3)
    # Step 0: 1 + 0.5 * 2, and the episode ends at step 1: nothing to bootstrap from.
    # Step 1: 2, ending right here. Step 2: 4 + 0.5 * 8 + 0.25 * 16, then 0.5^3 times the value at step 5.
    np.testing.assert_allclose(sums[:, 0], [2.0, 2.0, 12.0])
    np.testing.assert_allclose(discounts[:, 0], [0.0, 0.0, 0.125])


def test_importance_weights_of_the_prioritised_buffer_for_hand_set_priorities():
    buffer = fbx.make_prioritised_trajectory_buffer(
        add_batch_size=1,
        sample_batch_size=64,
        sample_sequence_length=1,
        period=1,
        min_length_time_axis=1,
        max_length_time_axis=4,
        priority_exponent=0.5,
    )

    @jax.jit  # one program (op by op, the buffer's operations compile about a hundred)
    def sample_and_weigh(key):
        state = buffer.init(jnp.zeros(()))
        state = buffer.add(state, jnp.arange(4.0)[None])
        state = buffer.set_priorities(state, jnp.arange(4), jnp.array([1.0, 4.0, 9.0, 16.0]))
        sample = buffer.sample(state, key)
        return sample, importance_weights(sample.probabilities, 0.4), importance_weights(sample.probabilities, 1.0)

    sample, weights_04, weights_1 = sample_and_weigh(jax.random.key(0))
    # Priority exponent 0.5: p^0.5 = 1, 2, 3, 4 of total 10, so P = 0.1, 0.2, 0.3, 0.4 for the N = 4 items.
    P = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(sample.probabilities, P[sample.indices], rtol=1e-6)
    np.testing.assert_array_equal(sample.experience[:, 0], sample.indices)
    assert set(np.asarray(sample.indices)) == {0, 1, 2, 3}  # stratified: 64 strata cover every item
    # beta = 0.4: w = (N P)^-0.4 = 0.4^-0.4, 0.8^-0.4, 1.2^-0.4, 1.6^-0.4 = 1.4427, 1.0934, 0.9297, 0.8285,
    # over the largest (item 0's): 1, 0.7579, 0.6444, 0.5743.
    w = (4 * P) ** -0.4
    expected = (w / w.max())[sample.indices]
    np.testing.assert_allclose(weights_04, expected, rtol=1e-5)
    np.testing.assert_allclose(importance_weights(jnp.asarray(P), 0.4), [1.0, 0.7579, 0.6444, 0.5743], atol=1e-4)
    # beta = 1 (the end of training) fully corrects: w = P(0) / P(i) = 1, 1/2, 1/3, 1/4.
    np.testing.assert_allclose(weights_1, (0.1 / P)[sample.indices], rtol=1e-5)
    # A window drawn at probability 0 (no longer valid) gets no weight.
    np.testing.assert_allclose(importance_weights(jnp.array([0.0, 0.1, 0.4]), 1.0), [0.0, 1.0, 0.25])


@pytest.mark.slow
def test_noisy_layer_mean_is_deterministic_and_noise_changes_outputs():
    layer = NoisyDense(6, sigma0=0.5)
    x = jnp.ones((2, 4))  # two identical rows
    params = jax.jit(layer.init)(jax.random.key(0), x)["params"]
    # Fortunato et al.'s factorised init: mu ~ U(+-1/sqrt(fan_in)), sigma = sigma0 / sqrt(fan_in).
    assert np.abs(params["kernel"]).max() <= 0.5 and np.abs(params["bias"]).max() <= 0.5
    np.testing.assert_allclose(params["sigma_kernel"], 0.25)
    np.testing.assert_allclose(params["sigma_bias"], 0.25)
    mean = jax.jit(layer.apply)({"params": params}, x)
    np.testing.assert_allclose(mean, x @ params["kernel"] + params["bias"], rtol=1e-6)
    noisy = NoisyDense(6, sigma0=0.5, noise=True)
    apply_noisy = jax.jit(lambda x, key: noisy.apply({"params": params}, x, rngs={"noise": key}))
    a, again, b = (apply_noisy(x, jax.random.key(k)) for k in (1, 1, 2))
    np.testing.assert_array_equal(a, again)  # the noise is the rng's, nothing else
    assert not np.allclose(a, b) and not np.allclose(a, mean)
    np.testing.assert_array_equal(a[0], a[1])  # one draw per forward pass, shared by its rows
    # The noise has mean zero: averaged over many draws the output approaches the mean network's.
    draws = jax.jit(jax.vmap(lambda k: apply_noisy(x[:1], k)))(jax.random.split(jax.random.key(3), 4000))
    np.testing.assert_allclose(draws.mean(0)[0], mean[0], atol=0.05)


@pytest.mark.slow
def test_noise_per_world_is_the_factorised_kernel_applied_row_by_row():
    layer = NoisyDense(6, sigma0=0.5)
    params = {"params": jax.jit(layer.init)(jax.random.key(0), jnp.ones((1, 1, 4)))["params"]}
    params["params"]["sigma_bias"] = jnp.linspace(0.1, 0.6, 6)  # away from the init, so the bias noise shows
    shared, per_row = NoisyDense(6, sigma0=0.5, noise=True), NoisyDense(6, sigma0=0.5, noise=True, per_row=True)
    # One row, same key: the same draws, so x (mu + sigma e_in e_out^T) + mu_b + sigma_b e_out computed as
    # one kernel and as x mu + ((x e_in) sigma + sigma_b) e_out must agree.
    x = jax.random.normal(jax.random.key(1), (1, 1, 4))
    rngs = {"noise": jax.random.key(2)}

    @jax.jit  # the layers' outputs below as one program (op by op, some fifty small ones)
    def outputs(x):
        return (
            (per_row.apply(params, x, rngs=rngs), shared.apply(params, x, rngs=rngs)),
            per_row.apply(params, jnp.ones((3, 4, 2, 4)), rngs=rngs),
            (per_row.apply(params, jnp.ones((1, 4000, 4)), rngs=rngs), layer.apply(params, jnp.ones((1, 1, 4)))),
        )

    (one_row, one_row_shared), out, (draws, mean) = outputs(x)
    np.testing.assert_allclose(one_row, one_row_shared, rtol=1e-5, atol=1e-6)
    # Identical rows (3 steps x 4 worlds, with an axis in between as the frame stack has): each
    # (step, world) draws its own noise, broadcast over the axis in between.
    assert out.shape == (3, 4, 2, 6)
    assert len({tuple(np.round(np.asarray(r), 6)) for r in out[:, :, 0].reshape(12, 6)}) == 12
    np.testing.assert_array_equal(out[:, :, 0], out[:, :, 1])
    with pytest.raises(ValueError, match="per_row noise needs inputs"):
        per_row.apply(params, jnp.ones((4, 4)), rngs=rngs)
    np.testing.assert_allclose(draws[0].mean(0), mean[0, 0], atol=0.05)


# --- runs ----------------------------------------------------------------------------------------------


def test_cross_entropy_and_kl_by_hand():
    # Target (1/2, 1/2, 0) against a prediction (1/4, 1/2, 1/4):
    # cross-entropy = -(1/2 ln 1/4 + 1/2 ln 1/2) = 1.5 ln 2 = 1.03972;
    # the target's entropy is ln 2 (its 0 ln 0 is 0), so KL = 0.5 ln 2 = 0.34657.
    target = jnp.array([[0.5, 0.5, 0.0], [0.25, 0.5, 0.25]])
    logits = jnp.log(jnp.array([[0.25, 0.5, 0.25], [0.25, 0.5, 0.25]])) + 3.0  # a shift changes no softmax
    cross_entropy, kl = cross_entropy_and_kl(target, logits)
    np.testing.assert_allclose(cross_entropy, [1.5 * np.log(2), 1.5 * np.log(2)], rtol=1e-6)
    # The second row predicts its target exactly: KL 0, cross-entropy its entropy 1.5 ln 2.
    np.testing.assert_allclose(kl, [0.5 * np.log(2), 0.0], atol=1e-6)


def test_loss_and_priorities_match_hand_computation_with_weights_double_q_and_an_episode_end():
    """`Rainbow.loss` on hand-set logits (the network is replaced by them): the double-Q bootstrap
    action, the projected target, the KL of the taken action, importance weights and priorities."""
    agent = _agent(atoms=3, v_min=0.0, v_max=2.0, n_step=1, sequence_length=1, gamma=0.5, reward_scale=2.0)
    c, a = agent.config.context, agent.env.num_actions  # 3 actions in 1D
    assert a == 3 and agent.config.sample_length == c + 2

    def logits(*rows):  # probabilities (action, atom) of one window -> log-probabilities
        return jnp.log(jnp.array(rows))

    eps = 1e-9  # "zero" probability, whose log stays finite
    # Window 0: the online network's greedy bootstrap action is 1 (expected 2 against 0); the
    # target network prefers action 0 (expected 2 against 0.5) but reads action 1: (1/2, 1/2, 0).
    # Window 1: its episode ends at the learning step (discount 0); its bootstrap is ignored.
    online_next = jnp.stack([logits([1, eps, eps], [eps, eps, 1], [1, eps, eps])] * 2)[None]
    target_next = jnp.stack([logits([eps, eps, 1], [0.5, 0.5, eps], [1, eps, eps])] * 2)[None]
    learning = jnp.stack(
        [logits([0.25, 0.5, 0.25], [1 / 3] * 3, [1 / 3] * 3), logits([1 / 3] * 3, [1 / 3] * 3, [0.25, 0.25, 0.5])]
    )[None]  # (1, S=2, A, atoms)
    agent.replayed_frames = lambda batch, obs: (None, None)
    agent.window_logits = lambda *args: (learning, online_next, target_next)

    rows = c + 2
    column = lambda *values: jnp.zeros((rows, 2)).at[c].set(jnp.array(values))
    batch = Step(
        obs=jnp.zeros((rows, 2, 1), jnp.int16),
        reset=jnp.zeros((rows, 2), bool),
        action=column(0, 2).astype(jnp.int8),
        reward=column(0.5, 1.0),
        done=column(0, 1).astype(bool),
    )
    weights = jnp.array([1.0, 0.5])  # the rewards are learned from as 1 and 2 (reward_scale 2)
    # Jitted: one program per config, which the loss reads when it traces (op by op, about a hundred).
    loss_of = lambda: jax.jit(lambda: agent.loss(None, None, batch, weights, None, None))()
    loss, (info, priority) = loss_of()
    # Window 0: 1 + 0.5 z over (1/2, 1/2, 0) = 1 (1/2), 1.5 (1/2, split 1/4 / 1/4 onto atoms 1 and
    # 2): target (0, 3/4, 1/4); the taken action 0 predicts (1/4, 1/2, 1/4):
    # KL = 3/4 ln(3/4 / 1/2) + 1/4 ln(1/4 / 1/4) = 0.75 ln 1.5 = 0.304099.
    # Window 1: reward 2, discount 0: target (0, 0, 1); action 2 predicts 1/2 there: KL = ln 2.
    kl = np.array([0.75 * np.log(1.5), np.log(2.0)])
    np.testing.assert_allclose(priority, kl, rtol=1e-5)
    np.testing.assert_allclose(loss, (1.0 * kl[0] + 0.5 * kl[1]) / 2, rtol=1e-5)  # 0.325337
    np.testing.assert_allclose(info["q_mean"], (1.0 + 1.25) / 2, rtol=1e-5)  # expected returns of the taken actions

    # The cross-entropy priority adds the target's entropy: 3/4 ln 4/3 + 1/4 ln 4 = 0.562335 for window 0.
    agent.config = dataclasses.replace(agent.config, cross_entropy_priority=True)
    _, (_, priority) = loss_of()
    np.testing.assert_allclose(priority, kl + [0.75 * np.log(4 / 3) + 0.25 * np.log(4.0), 0.0], rtol=1e-5)

    # Without double Q the target network's own greedy action 0 is read: 1 + 0.5 * 2 = 2, target
    # (0, 0, 1), and window 0's KL becomes ln 4.
    agent.config = dataclasses.replace(agent.config, cross_entropy_priority=False, double_q=False)
    loss, (_, priority) = loss_of()
    np.testing.assert_allclose(priority, [np.log(4.0), np.log(2.0)], rtol=1e-5)
    np.testing.assert_allclose(loss, (np.log(4.0) + 0.5 * np.log(2.0)) / 2, rtol=1e-5)


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_cross_entropy_priority_changes_the_priority_not_the_loss():
    kl_agent = _agent()
    state = jax.jit(kl_agent.init)(jax.random.key(0))
    state, _ = jax.jit(lambda s: kl_agent.train_chunk(s, kl_agent.env_params, 1))(state)
    sample = kl_agent.buffer.sample(state.buffer, jax.random.key(1))
    batch = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), sample.experience)
    weights = jnp.ones(sample.probabilities.shape)
    keys = jax.random.split(jax.random.key(2))
    results = [
        agent.loss(state.params, state.target_params, batch, weights, *keys)
        for agent in (kl_agent, _agent(cross_entropy_priority=True))
    ]
    (kl_loss, (_, kl)), (ce_loss, (_, ce)) = results
    np.testing.assert_allclose(kl_loss, ce_loss, rtol=1e-6)
    np.testing.assert_allclose(kl_loss, kl.mean(), rtol=1e-5)
    # The cross-entropy is the KL plus the target's entropy, which a projected target always has here.
    assert np.all(np.asarray(ce) > np.asarray(kl) + 1e-3)


@pytest.mark.parametrize(
    "options",
    [pytest.param(o, marks=pytest.mark.slow) for o in (dict(), dict(sequence_length=3, n_step=2, frame_stack=2))],
)
def test_window_logits_are_the_full_windows_rows_the_loss_reads(options):
    """The loss computes only the learning rows and the rows n steps later; under the same noise
    keys they equal those rows of the whole window read at once (the network is feed-forward)."""
    agent = _agent(**options)
    cfg = agent.config
    state = jax.jit(agent.init)(jax.random.key(0))
    state, _ = jax.jit(lambda s: agent.train_chunk(s, agent.env_params, 1))(state)
    batch = jax.tree.map(
        lambda x: jnp.swapaxes(x, 0, 1), agent.buffer.sample(state.buffer, jax.random.key(1)).experience
    )
    frames, resets = agent.replayed_frames(batch, batch.obs.astype(jnp.float32))
    assert frames.shape[0] == cfg.sequence_length + cfg.n_step
    target_params = jax.tree.map(lambda x: 1.1 * x, state.params)  # a target that differs from the online network
    key_online, key_target = jax.random.split(jax.random.key(2))
    learning, bootstrap_online, bootstrap_target = agent.window_logits(
        state.params, target_params, frames, resets, key_online, key_target
    )
    carry = agent.initial_carry(frames.shape[1])
    _, online = agent.logits(state.params, carry, frames, resets, key_online)
    _, target = agent.logits(target_params, carry, frames, resets, key_target)
    length, n = cfg.sequence_length, cfg.n_step
    np.testing.assert_allclose(learning, online[:length], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(bootstrap_online, online[n:], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(bootstrap_target, target[n:], rtol=1e-5, atol=1e-5)
    assert not np.allclose(bootstrap_online, bootstrap_target, atol=1e-3)  # the two networks and keys differ


@pytest.fixture(scope="module")
def trained_1d():
    agent = _agent()
    state = jax.jit(agent.init)(jax.random.key(0))
    state, metrics = jax.jit(lambda s: agent.train_chunk(s, agent.env_params, 4))(state)
    return agent, state, jax.device_get(metrics)


@pytest.mark.slow
def test_rainbow_trains_with_finite_losses_and_updates_priorities(trained_1d):
    agent, state, metrics = trained_1d
    assert np.all(np.isfinite(metrics["loss"])) and np.all(metrics["loss"] > 0)
    assert np.all(np.isfinite(metrics["q_mean"])) and np.all(metrics["epsilon"] == 0.0)
    assert int(state.gradient_step) == 4
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))
    # The sampled windows got their KL as priority: no longer all the initial maximum of 1.
    tree = state.buffer.sum_tree_state
    leaves = np.asarray(tree.nodes[-(2**tree.tree_depth) :][: tree.capacity])
    assert len(np.unique(leaves[leaves > 0])) > 1 and float(tree.max_recorded_priority) != 1.0


@pytest.mark.slow
def test_greedy_policy_is_the_noise_free_mean_network(trained_1d):
    agent, state, _ = trained_1d
    policy = agent.policy(state.params)

    @jax.jit  # one program (op by op, some eighty)
    def actions_and_q_values(params):
        obs, _ = agent.env.reset(jax.random.key(0), agent.env_params)
        memory = policy.init(jax.random.key(0), None)
        actions = jnp.stack([policy.act(params, memory, obs, jax.random.key(k))[0] for k in range(5)])
        frames = agent.layout.acting_inputs(obs, memory)[None, None, None]
        carry = agent.network.initial_carry(1)
        _, logits = agent.network.apply(params, carry, frames, jnp.ones((1, 1), bool))
        _, noisy_q = agent.q_values(params, carry, frames, jnp.ones((1, 1), bool), jax.random.key(1))
        return actions, agent.expected(logits), noisy_q

    actions, mean_q, noisy_q = actions_and_q_values(policy.params)
    actions = set(np.asarray(actions).tolist())
    assert len(actions) == 1  # the acting key draws nothing
    assert actions == {int(jnp.argmax(mean_q[0, 0]))}
    # While the acting network's noise does move the Q-values.
    assert not np.allclose(noisy_q, mean_q)


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_acting_draws_noise_for_each_world_apart(trained_1d):
    """Worlds that see the same input get different Q-values when acting (each its own noise
    draw); one world alone gets the values of the network under the batch's one draw."""
    agent, state, _ = trained_1d
    obs, _ = agent.env.reset(jax.random.key(0), agent.env_params)
    memory = agent.policy(state.params).init(jax.random.key(0), None)
    frames = jnp.broadcast_to(agent.layout.acting_inputs(obs, memory), (1, 4, 1, agent.layout.obs_size))
    carry, resets, key = agent.network.initial_carry(4), jnp.ones((1, 4), bool), jax.random.key(5)
    (_, q), _ = agent.acting_scores(state.params, carry, frames, resets, key[None], {})
    assert q.shape == (1, 4, agent.env.num_actions)
    assert not np.allclose(q[0, 0], q[0, 1]) and not np.allclose(q[0, 2], q[0, 3])
    _, mean = agent.q_values(state.params, carry, frames, resets)
    assert not np.allclose(q, mean)
    (_, one), _ = agent.acting_scores(state.params, carry[:1], frames[:, :1], resets[:, :1], key[None], {})
    _, shared = agent.q_values(state.params, carry[:1], frames[:, :1], resets[:, :1], key)
    np.testing.assert_allclose(one, shared, rtol=1e-5, atol=1e-5)


@pytest.mark.slow  # a whole driver run (minutes on 2 cores): `pytest -m slow`
def test_two_seeds_through_the_driver_compile_once(tmp_path, monkeypatch):
    from agents.training.driver import read_metrics, train

    traces = {"loss": 0, "_env_step": 0}
    for name in traces:
        original = getattr(Rainbow, name)

        def counted(self, *args, _original=original, _name=name, **kwargs):
            traces[_name] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(Rainbow, name, counted)
    config = make_config("rainbow", "1d-static-step", **TINY, seeds=2)  # two equal chunks: one program
    _, state = train(config, tmp_path, progress=False)
    # The loss is traced twice in the one program: for the learning branch and for the waiting
    # branch's metric shapes (`agents.common.offpolicy`'s update); a second chunk traces nothing more.
    assert traces == {"loss": 2, "_env_step": 1}
    assert state.params["params"]["NoisyDense_0"]["kernel"].shape[0] == 2
    first, second = (jax.tree.map(lambda x: x[i], state.params) for i in (0, 1))
    assert not np.array_equal(first["params"]["NoisyDense_0"]["kernel"], second["params"]["NoisyDense_0"]["kernel"])
    records = read_metrics(tmp_path)
    assert [r["chunk"] for r in records] == [0, 1]
    assert all(np.all(np.isfinite(r["loss"])) for r in records)


@pytest.mark.slow
@pytest.mark.parametrize(
    "options",
    [
        pytest.param(
            dict(
                noisy=False,
                eps_start=1.0,
                eps_end=0.1,
                double_q=False,
                dueling=False,
                n_step=1,
                priority_exponent=0.0,
                cross_entropy_priority=True,
                anneal_lr=True,
                layer_norm=True,
            ),
            id="ablations",
        ),
        pytest.param(dict(max_steps=20), id="2d-dynamic", marks=pytest.mark.slow),
    ],
)
def test_ablated_and_other_configurations_train(options):
    task = "2d-dynamic-dense" if options.get("max_steps") == 20 else "1d-static-gauss"
    agent = _agent(task, **options)
    state = jax.jit(agent.init)(jax.random.key(1))
    state, metrics = jax.jit(lambda s: agent.train_chunk(s, agent.env_params, 3))(state)
    assert np.all(np.isfinite(metrics["loss"])) and int(state.gradient_step) == 3
    if not agent.config.noisy:
        assert "NoisyDense_0" not in state.params["params"] and metrics["epsilon"][0] > 0.0


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_layer_norm_normalises_every_hidden_layer_and_is_off_by_default():
    # Four hidden ReLUs (two in the encoder, one per dueling stream), each after a LayerNorm; with
    # them the output no longer depends on the scale of the first layer's pre-activations.
    def init(**options):
        agent = build_algorithm(make_config("rainbow", "1d-static-sin", num_envs=8, **options))
        return agent, jax.jit(agent.init)(jax.random.key(0)).params

    def layer_norms(params):  # the modules' paths, without their scale and bias leaves
        paths = [path[:-1] for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]]
        return {path for path in paths if "LayerNorm" in jax.tree_util.keystr(path)}

    assert not layer_norms(init()[1])
    agent, params = init(layer_norm=True)
    assert len(layer_norms(params)) == 4
    frames = jax.random.uniform(jax.random.key(1), (1, 5, 1, agent.layout.obs_size))
    carry, resets = agent.network.initial_carry(5), jnp.ones((1, 5), bool)
    first = params["params"]["ObservationEncoder_0"]["NoisyDense_0"]
    scaled = jax.tree.map(lambda x: x, params)
    scaled["params"]["ObservationEncoder_0"]["NoisyDense_0"] = jax.tree.map(lambda x: 7.0 * x, first)
    np.testing.assert_allclose(
        agent.q_values(scaled, carry, frames, resets)[1],
        agent.q_values(params, carry, frames, resets)[1],
        rtol=1e-4,
        atol=1e-4,
    )


# --- config -----------------------------------------------------------------------------------------------


def test_defaults_are_the_papers_settings():
    # The config class's defaults are the paper's appendix (every task's tuned entry departs from them).
    config = RainbowConfig()
    assert (config.v_min, config.v_max, config.atoms) == (-5.0, 35.0, 101)
    assert (config.sigma0, config.n_step, config.priority_exponent, config.importance_exponent) == (0.1, 3, 0.5, 0.4)
    assert config.noisy and config.dueling and config.double_q and config.eps_start == config.eps_end == 0.0
    assert (config.buffer_size, config.hidden_size, config.learning_rate) == (10_000, 128, 5e-5)
    assert make_config("rainbow", "1d-static-sin").learning_rate == 5e-5
    for task in ("3d-static-dense", "3d-static-sparse", "3d-dynamic-dense", "3d-dynamic-sparse"):
        assert make_config("rainbow", task).learning_rate == 1e-4
    agent = build_algorithm(make_config("rainbow", "1d-static-sin", num_envs=8))
    # Three noisy hidden layers of 128 (two in the encoder, one in each dueling stream), 101 atoms per action.
    params = jax.eval_shape(agent.init, jax.random.key(0)).params["params"]
    assert params["ObservationEncoder_0"]["NoisyDense_1"]["kernel"].shape == (128, 128)
    assert params["NoisyDense_0"]["kernel"].shape == (128, 128) and params["NoisyDense_3"]["kernel"].shape == (
        128,
        3 * 101,
    )
    assert agent.beta(0) == pytest.approx(0.4) and agent.beta(agent.config.total_steps) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "options,message",
    [
        (dict(v_min=5.0, v_max=5.0), r"v_min \(5.0\) must be below v_max \(5.0\)"),
        (dict(atoms=1), "atoms must be an int >= 2"),
        (dict(priority_exponent=1.5), r"priority_exponent must be a number in \[0, 1\]"),
        (dict(sigma0=-0.1), "sigma0 must be a number >= 0"),
    ],
)
def test_config_errors_are_clear(options, message):
    with pytest.raises(ValueError, match=message):
        make_config("rainbow", "1d-static-sin", **options)


# --- resume and the command line ------------------------------------------------------------------------


@pytest.mark.slow  # three compilations of a whole run on a 2-core CPU
def test_resume_gives_the_uninterrupted_result_and_the_checkpoint_evaluates(tmp_path):
    from agents.training.driver import train
    from agents.training.trained import checkpoint_policy
    from snac_jax.evaluation import evaluate_task

    config = make_config("rainbow", "1d-static-sin", **TINY)
    _, full = train(config, tmp_path / "full", progress=False)
    train(config, tmp_path / "cut", progress=False, stop_after_chunks=1)
    _, resumed = train(config, tmp_path / "cut", resume=True, progress=False)
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed)):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    result = evaluate_task("1d-static-sin", lambda env: checkpoint_policy(env, tmp_path / "cut"), static_episodes=4)
    assert result.episodes == 4 and 0.0 <= result.mean <= 1.0


@pytest.mark.slow  # a training and an evaluation subprocess
def test_cli_trains_rainbow_and_evaluates_it(tmp_path):
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
        "rainbow",
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
        "--atoms",
        "11",
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
        "--seed",
        "2",
    ]  # two different greedy policies
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "replay on device" in result.stderr
    for name in ("config.json", "metrics.jsonl", "curve.png", "eval.json"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "config.json").read_text())
    assert saved["algorithm"] == "rainbow" and saved["seeds"] == 2
    check_each_seed_evaluates_from_the_checkpoint(result.stdout, out, "1d-static-step", env)
    bad = subprocess.run(
        [sys.executable, "-m", "snac_jax.cli", "train", "rainbow", "--huber-delta", "2"],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert bad.returncode != 0 and "unrecognized arguments: --huber-delta" in bad.stderr

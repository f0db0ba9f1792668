"""`safe_drops`: the drops that would wall the robot in, refused from the window (agents.common.safe_drops)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.common.safe_drops import allowed_actions, neighbour_drop_targets
from agents.learners.pqn import PQN, PQNConfig
from agents.research.pqn_aux import PQNAux, PQNAuxConfig
from snac_jax import make
from snac_jax.observation import LANDMARK_VALUE

CONFIG_3D = make("3d-static-dense")[0].config
# The 3D window is 7x7, row-major; the robot's four neighbours (left, right, down, up).
LEFT, RIGHT, DOWN, UP = 3 * 7 + 2, 3 * 7 + 4, 4 * 7 + 3, 2 * 7 + 3


def window(left, right, down, up):
    cells = np.zeros(49, np.float32)
    cells[[LEFT, RIGHT, DOWN, UP]] = left, right, down, up
    return jnp.asarray(cells)


def test_each_neighbour_drop_targets_its_neighbour_in_the_window():
    # 3D's table: moves 0-3, drops 4-7 on (r, c-1), (r, c+1), (r+1, c), (r-1, c) (SPEC §3).
    assert neighbour_drop_targets(CONFIG_3D).tolist() == [-1, -1, -1, -1, LEFT, RIGHT, DOWN, UP]


@pytest.mark.parametrize(
    "neighbours, refused",
    [
        ((2, -1, 1, 0), [7]),  # up is the only free neighbour: the drop on it is refused
        ((0, -1, 1, 0), []),  # two free: a drop on either leaves the other
        ((2, -1, 1, LANDMARK_VALUE), []),  # a landmark is free, but a drop on it lands nowhere (SPEC §9)
        ((2, -1, 1, 3), []),  # already stuck: stacking closes nothing new
        ((LANDMARK_VALUE, -1, 1, 0), []),  # up and the landmark on the left are free
    ],
)
def test_only_a_drop_on_the_last_free_neighbour_is_refused(neighbours, refused):
    allowed = np.asarray(allowed_actions(CONFIG_3D, window(*neighbours)))
    assert [a for a in range(8) if not allowed[a]] == refused


def test_allowed_actions_batch_over_leading_axes():
    windows = jnp.stack([window(2, -1, 1, 0), window(0, 0, 0, 0)])[None]
    allowed = allowed_actions(CONFIG_3D, windows)
    assert allowed.shape == (1, 2, 8)
    assert not allowed[0, 0, 7] and allowed[0, 1].all()


def test_safe_drops_without_the_obstacle_rule_is_refused_naming_the_switch():
    with pytest.raises(ValueError, match=r"safe_drops needs the obstacle rule \(3D, or 2D with obstacles=true\)"):
        PQNConfig(task="2d-static-dense", safe_drops=True).validate()
    PQNConfig(task="2d-static-dense", safe_drops=True, switches="obstacles=true").validate()


def tiny(safe_drops: bool) -> PQN:
    return PQN(
        PQNConfig(
            task="3d-static-dense",
            num_envs=8,
            num_minibatches=2,
            rollout_steps=32,
            hidden_size=8,
            rnn_size=8,
            eps_start=1.0,
            eps_end=1.0,
            stagger_starts=False,
            safe_drops=safe_drops,
        )
    )


@pytest.mark.slow
@pytest.mark.parametrize("safe_drops", [True, False])
def test_random_exploration_never_walls_the_robot_in_with_safe_drops(safe_drops):
    # Every action random: at the start corner two neighbours are padding, so two drops wall the
    # robot in, and the next action ends the episode. 3D's brick budget is far beyond 128 steps, so
    # every termination here is the stuck rule's.
    pqn = tiny(safe_drops)
    state, rollout = pqn.init(jax.random.key(0)), jax.jit(pqn.rollout)
    terminations = 0
    for _ in range(4):
        state, batch, _ = rollout(state, pqn.env_params)
        terminations += int(batch.terminated.sum())
    assert (terminations == 0) if safe_drops else (terminations > 0)


@pytest.mark.parametrize("safe_drops", [True, False])
def test_the_greedy_policy_never_takes_a_refused_drop(safe_drops):
    pqn = tiny(safe_drops)
    params = pqn.init(jax.random.key(0)).params
    head = params["params"]["Dense_0"]  # the Q head: action 6 (drop down) far above the rest
    params = {"params": {**params["params"], "Dense_0": {**head, "bias": head["bias"].at[6].add(1e3)}}}
    policy = pqn.policy(params)
    env, env_params = pqn.env, pqn.env_params
    obs, _ = env.reset(jax.random.key(1), env_params)
    obs = obs.at[RIGHT].set(1.0)  # at the corner (left and up are padding), right holds a brick: down is the way out
    memory = policy.init(jax.random.key(2), None)
    action, _ = policy.act(params, memory, obs, jax.random.key(3))
    assert (int(action) != 6) if safe_drops else (int(action) == 6)


def with_drop_down_first(params):
    """The Q head's bias for action 6 (drop down) raised far above every other action."""
    head = params["params"]["Dense_0"]
    return {"params": {**params["params"], "Dense_0": {**head, "bias": head["bias"].at[6].add(1e3)}}}


@pytest.mark.slow
@pytest.mark.parametrize(
    "learner, config", [(PQN, PQNConfig), pytest.param(PQNAux, PQNAuxConfig, marks=pytest.mark.slow)]
)
@pytest.mark.parametrize("safe_drops", [pytest.param(True, marks=pytest.mark.slow), False])
def test_the_greedy_rollout_and_its_bootstrap_skip_the_refused_drop(learner, config, safe_drops):
    # Greedy (epsilon 0) from staggered starts, the head preferring the drop down everywhere: where
    # down is the last free neighbour, the rollout must act otherwise and bootstrap from the best
    # allowed action, not from the refused drop's 1e3 (pqn-aux's rollout is its own: both checked).
    pqn = learner(
        config(
            task="3d-static-dense",
            num_envs=32,
            num_minibatches=2,
            rollout_steps=64,
            hidden_size=8,
            rnn_size=8,
            eps_start=0.0,
            eps_end=0.0,
            stagger_starts=True,
            safe_drops=safe_drops,
        )
    )
    state = pqn.init(jax.random.key(0))
    state = state.replace(params=with_drop_down_first(state.params))
    after, batch, _ = jax.jit(pqn.rollout)(state, pqn.env_params)
    window = pqn.layout.window_size
    refused = ~allowed_actions(pqn.env.config, batch.obs[..., :window])[..., 6]
    assert refused.any()
    if not safe_drops:
        assert (batch.action[refused] == 6).all()
        return
    assert not (batch.action[refused] == 6).any()
    assert batch.value[refused].max() < 100
    refused_last = ~allowed_actions(pqn.env.config, after.worlds.obs[..., :window])[..., 6]
    assert refused_last.any()
    targets = pqn.targets(state.params, batch, after.worlds)
    assert targets[-1][refused_last & ~(batch.terminated[-1] | batch.truncated[-1])].max() < 100

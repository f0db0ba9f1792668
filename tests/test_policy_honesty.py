"""Every learner's greedy policy acts on its observations and its own memory alone (SPEC §12):
the evaluator's episode function (`snac_jax.evaluation._run_episodes`, the one the protocol of
SPEC §8 scores with) runs the policy on a world whose state lies about what the robot cannot
observe (the true position, the grid, the design, the brick budget and the IoU sums) while every
observation stays the true world's. Actions and policy memory must match step for step those of
the same episode told the truth.

Why through the evaluator rather than by reading `act`'s signature: the channels a policy could
read privileged state through are whatever the evaluator hands it (`init` gets `state.design`,
hidden on a static task; `act` gets the observation), and a signature says nothing about what a
function closes over or keeps in its memory. The networks are untrained: each learner is compared
under DRAWS draws of random weights, at least one of which must act in more than one way (a
constant policy proves nothing), and `test_the_check_catches_a_policy_that_reads_the_design`
shows that a policy reading the design its `init` is handed fails the comparison. The team
policy of `ippo` (SPEC §13) is run through its own episode loop, `snac_jax.multi.run_episode`.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.training.registry import ALGORITHMS, build_algorithm, make_config
from snac_jax.env import SNACEnv
from snac_jax.evaluation import _run_episodes
from snac_jax.multi import MultiSNACEnv
from snac_jax.multi.episodes import MultiPolicy, run_episode
from snac_jax.policy import Policy

STEPS = 20  # the episodes' step limit
GAIN = 2.0  # the scale of the random weights
DRAWS = 16  # draws of random parameters compared per learner
PPO = dict(
    total_steps=2 * 16 * 8,
    num_envs=16,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=1,
    hidden_size=16,
    rnn_size=16,
    recurrent=True,
)
DRQN = dict(
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
REPLAY = dict(
    num_envs=8,
    rollout_steps=8,
    batch_size=16,
    hidden_size=16,
    learning_starts=0,
    gradient_steps=1,
    total_steps=4 * 64,
    buffer_size=8 * 40,
)
TINY = {
    "ppo": PPO,
    "ppo-privileged": PPO,
    "pqn": PPO,
    "pqn-aux": PPO,
    "pqn-belief": PPO,
    "dqn": dict(REPLAY, frame_stack=2),  # the stacked frames are memory too
    "drqn": DRQN,
    "drqn-her": DRQN,
    "drqn-aux": DRQN,
    "rainbow": dict(REPLAY, frame_stack=1, atoms=11),
    "sac": dict(REPLAY, hidden_size=None, hidden_sizes="16,16"),
    "ippo": dict(num_envs=4, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8, robots=2),
}
SINGLE = [name for name in ALGORITHMS if name != "ippo"]
CASES = [(name, task) for name in SINGLE for task in ("2d-static-sparse", "2d-dynamic-sparse")]
CASES += [("ppo", "3d-static-sparse")]
# PPO, PQN and pqn-belief in the default suite; every learner in `pytest -m slow` (each compiles its learner).
DEFAULT_SUITE = {"ppo", "pqn", "pqn-belief"}
CASES = [case if case[0] in DEFAULT_SUITE else pytest.param(*case, marks=pytest.mark.slow) for case in CASES]


# --- a world that lies about its state --------------------------------------------------------------


def _lie(state, plan_shape, lying):
    """`state` with its unobservable parts changed where `lying`: the position shifted cyclically
    by half the plan (still on the plan), one more brick on every plan cell of the grid and of the
    design, one more brick in the budget, and the IoU sums as -1 - x (negative: the mark of a lie)."""
    shift = jnp.array([n // 2 for n in plan_shape], jnp.int32)
    lied = state.replace(
        position=(state.position + shift) % jnp.array(plan_shape, jnp.int32),
        grid=jnp.where(state.grid >= 0, state.grid + 1, state.grid).astype(state.grid.dtype),
        design=(state.design + 1).astype(state.design.dtype),
        max_bricks=state.max_bricks + 1,
        overlap=-1 - state.overlap,
        union=-1 - state.union,
    )
    return jax.tree.map(lambda a, b: jnp.where(lying, a, b), lied, state)


def _truth(state, plan_shape):
    """The true state behind `state`, lied about or not (`_lie`'s inverse)."""
    lying = state.union < 0
    shift = jnp.array([n // 2 for n in plan_shape], jnp.int32)
    true = state.replace(
        position=(state.position - shift) % jnp.array(plan_shape, jnp.int32),
        grid=jnp.where(state.grid >= 0, state.grid - 1, state.grid).astype(state.grid.dtype),
        design=(state.design - 1).astype(state.design.dtype),
        max_bricks=state.max_bricks - 1,
        overlap=-1 - state.overlap,
        union=-1 - state.union,
    )
    return jax.tree.map(lambda a, b: jnp.where(lying, a, b), true, state)


class Lying(SNACEnv):
    """`env`, except that an episode reset to design index 1 carries a lying state (`_lie`) from its
    reset to its end. Every step runs on the true state and observes it, so both episodes see
    the same observations; only what the evaluator hands a policy besides them differs."""

    def __init__(self, env: SNACEnv):
        super().__init__(env.config, env.default_params)

    def __hash__(self) -> int:
        return hash(("lying", self.config))

    def __eq__(self, other: object) -> bool:
        return type(other) is Lying and other.config == self.config

    def reset_to_design(self, key, params, design_index):
        obs, state = super().reset_to_design(key, params, design_index)
        return obs, _lie(state, self.config.plan_shape, design_index == 1)

    def step_with_stride(self, state, action, stride, params):
        lying = state.union < 0
        obs, state, reward, terminated, info = super().step_with_stride(
            _truth(state, self.config.plan_shape), action, stride, params
        )
        return obs, _lie(state, self.config.plan_shape, lying), reward, terminated, info


class LyingTeam(MultiSNACEnv):
    """`Lying` for several robots: the shared world's state lies on design index 1."""

    def __hash__(self) -> int:
        return hash(("lying", super().__hash__()))

    def __eq__(self, other: object) -> bool:
        return type(other) is LyingTeam and super().__eq__(other)

    def reset_to_design(self, key, design_index, params=None):
        obs, state = super().reset_to_design(key, design_index, params)
        return obs, state.replace(world=_lie(state.world, self.config.plan_shape, design_index == 1))

    def step_env(self, key, state, actions, params=None):
        lying = state.world.union < 0
        obs, state, rewards, dones, infos = super().step_env(
            key, state.replace(world=_truth(state.world, self.config.plan_shape)), actions, params
        )
        return obs, state.replace(world=_lie(state.world, self.config.plan_shape, lying)), rewards, dones, infos


def _twice(params, design):
    """`params` whose designs are `design` twice: index 0 the truth, index 1 the lie."""
    return params.replace(
        designs=jnp.stack([design, design]),
        design_max_bricks=jnp.repeat(params.design_max_bricks[:1], 2),
        design_volume=jnp.repeat(params.design_volume[:1], 2),
    )


# --- a policy that writes down what it did ------------------------------------------------------------


def _keep(log, lying, t, obs, action, memory):
    log[(bool(lying), int(t))] = (np.asarray(obs), np.asarray(action), [np.asarray(x) for x in jax.tree.leaves(memory)])


def _recorded(policy, true_design, log, kind=Policy):
    """`policy` writing (observation, action, memory after acting) per step into `log`, keyed by
    (lied to?, step). Whether it is lied to is read off the design its `init` is handed."""

    def init(key, design):
        return {
            "inner": policy.init(key, design),
            "t": jnp.zeros((), jnp.int32),
            "lying": jnp.any(design != true_design),
        }

    def act(params, memory, obs, key):
        action, inner = policy.act(params, memory["inner"], obs, key)
        jax.debug.callback(partial(_keep, log), memory["lying"], memory["t"], obs, action, inner)
        return action, {"inner": inner, "t": memory["t"] + 1, "lying": memory["lying"]}

    return kind(init, act, policy.params, policy.name)


def _compare(log, out):
    """The truth's and the lie's records in `log` and outcomes `out` (episode 0 told the truth, 1
    lied to): equal step for step, and the episodes as long. The told episode's actions."""
    told = {t: v for (lying, t), v in log.items() if not lying}
    lied = {t: v for (lying, t), v in log.items() if lying}
    for t in sorted(set(told) & set(lied)):
        (obs, action, memory), (obs_lied, action_lied, memory_lied) = told[t], lied[t]
        np.testing.assert_array_equal(obs, obs_lied, err_msg=f"step {t}: the observations differ")
        np.testing.assert_array_equal(action, action_lied, err_msg=f"step {t}: the actions differ")
        for leaf, leaf_lied in zip(memory, memory_lied, strict=True):
            np.testing.assert_array_equal(leaf, leaf_lied, err_msg=f"step {t}: the policy memory differs")
    lengths = np.asarray(out.length)
    assert lengths[0] == lengths[1], lengths  # both ended together
    assert sorted(told) == sorted(lied) == list(range(int(lengths[0])))
    returns = np.asarray(out.team_return if hasattr(out, "team_return") else out.episode_return)
    np.testing.assert_array_equal(returns[0], returns[1])
    return np.array([told[t][1] for t in sorted(told)])


def _random_params(shapes, seed):
    """Parameters of `shapes` drawn at random: each weight ~ N(0, GAIN^2 / fan_in), each vector
    ~ N(0, 1/4). Untrained, and unlike a fresh init (small output layers), every output moves
    with every input."""
    rng = np.random.default_rng(seed)

    def draw(leaf):
        if not jnp.issubdtype(leaf.dtype, jnp.floating):
            return jnp.zeros(leaf.shape, leaf.dtype)
        scale = GAIN / np.sqrt(np.prod(leaf.shape[:-1])) if len(leaf.shape) >= 2 else 0.5
        return jnp.asarray(scale * rng.standard_normal(leaf.shape), leaf.dtype)

    return jax.tree.map(draw, shapes)


def _learner(name, task):
    """The tiny learner, its greedy policy and its parameters' shapes (from `eval_shape`: nothing of
    the learner is compiled)."""
    agent = build_algorithm(make_config(name.split()[0], task, **TINY[name], max_steps=STEPS))
    shapes = jax.eval_shape(agent.init, jax.random.key(0)).params
    return agent, agent.policy(_random_params(shapes, 0)), shapes


def _evaluator(agent, policy, log):
    """`run(params)`: the evaluator's two episodes of `policy` with `params` on the agent's task,
    episode 0 told the truth and 1 lied to, with the same key (the same strides); `policy`'s
    records in `log` (cleared first) and the outcomes returned. Compiled once: new parameters
    are an argument of the jitted loop, as when the evaluator scores a checkpoint."""
    design = agent.env_params.designs[0]
    recorded = _recorded(policy, design, log)
    env, params = Lying(agent.env), _twice(agent.env_params, design)
    keys, indices = jnp.stack([jax.random.key(0)] * 2), jnp.array([0, 1], jnp.int32)

    def run(policy_params):
        log.clear()
        out = _run_episodes(env, recorded.init, recorded.act, policy_params, params, keys, indices)
        jax.effects_barrier()
        assert np.all(np.asarray(out.invalid_actions) == 0)
        assert {lying for lying, _ in log} == {False, True}  # the lie reached the policy's `init`
        return out

    return run


def _honest_on_varied_episodes(run, log, shapes):
    """Every one of DRAWS draws of parameters acts alike told the truth and lied to, and at least one
    acts in more than one way in its episode: a constant policy, which no lie could move, is not
    taken as proof."""
    varied = 0
    for seed in range(DRAWS):
        actions = _compare(log, run(_random_params(shapes, seed)))
        varied += len({tuple(np.atleast_1d(a).tolist()) for a in actions}) > 1
    assert varied, f"none of {DRAWS} draws of parameters acted in more than one way: the comparisons proved little"


# --- the tests -------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("name,task", CASES)
def test_the_greedy_policy_ignores_the_state_it_cannot_observe(name, task):
    agent, policy, shapes = _learner(name, task)
    log = {}
    _honest_on_varied_episodes(_evaluator(agent, policy, log), log, shapes)


@pytest.mark.slow
def test_the_team_policy_ignores_the_state_it_cannot_observe():
    agent, policy, shapes = _learner("ippo", "2d-dynamic-sparse")
    team, design, log = agent.team_env, agent.env_params.designs[0], {}
    env = LyingTeam(team.single, team.num_agents, team.default_params)
    recorded, params = _recorded(policy, design, log, kind=MultiPolicy), _twice(agent.env_params, design)
    episodes = jax.jit(
        jax.vmap(
            lambda p, key, index: run_episode(env, recorded._replace(params=p), key, index, params),
            in_axes=(None, 0, 0),
        )
    )
    keys, indices = jnp.stack([jax.random.key(0)] * 2), jnp.array([0, 1], jnp.int32)

    def run(policy_params):
        log.clear()
        out = episodes(policy_params, keys, indices)
        jax.effects_barrier()
        return out

    _honest_on_varied_episodes(run, log, shapes)


class LyingTeamButDesign(LyingTeam):
    """`LyingTeam` whose lie leaves the design true: the handcrafted policy is handed the design
    (SPEC §11), so only the rest of the state it cannot observe is lied about."""

    def __hash__(self) -> int:
        return hash(("lying-but-design", super().__hash__()))

    def __eq__(self, other: object) -> bool:
        return type(other) is LyingTeamButDesign and MultiSNACEnv.__eq__(self, other)

    def reset_to_design(self, key, design_index, params=None):
        obs, state = super().reset_to_design(key, design_index, params)
        world = state.world
        return obs, state.replace(
            world=world.replace(design=jnp.where(world.union < 0, world.design - 1, world.design))
        )

    def step_env(self, key, state, actions, params=None):
        world = state.world
        lying = world.union < 0
        lied = state.replace(world=world.replace(design=jnp.where(lying, world.design + 1, world.design)))
        obs, state, rewards, dones, infos = super().step_env(key, lied, actions, params)
        world = state.world
        return (
            obs,
            state.replace(world=world.replace(design=jnp.where(lying, world.design - 1, world.design))),
            rewards,
            dones,
            infos,
        )


@pytest.mark.slow
@pytest.mark.parametrize(
    "task, robots", [("2d-dynamic-dense", 2), pytest.param("2d-static-dense", 4, marks=pytest.mark.slow)]
)
def test_the_handcrafted_split_ignores_the_state_it_cannot_observe(task, robots):
    """The handcrafted split (SPEC §13) acts from its observations, the design and its memory: on a
    world lying about the true positions, the grid, the budget and the IoU sums (not the design,
    which it is handed) its actions and memory match the truth's step for step."""
    from snac_jax import multi
    from snac_jax.policies.team import team_policy

    team = multi.make(task, num_robots=robots, max_steps=80, **({"test_design": 0} if "dynamic" in task else {}))
    env = LyingTeamButDesign(team.single, robots, team.default_params)
    policy, design = team_policy("handcrafted", team), team.default_params.designs[0]
    params, log = _twice(team.default_params, design), {}

    def recorded(lying):
        def act(p, memory, obs, key):
            actions, inner = policy.act(p, memory["inner"], obs, key)
            jax.debug.callback(partial(_keep, log), lying, memory["t"], obs, actions, inner)
            return actions, {"inner": inner, "t": memory["t"] + 1}

        init = lambda key, d: {"inner": policy.init(key, d), "t": jnp.zeros((), jnp.int32)}
        return MultiPolicy(init, act, policy.params, policy.name)

    def episode(lying):  # design index 1 is the lying world's; the same key, so the same strides
        recorded_policy = recorded(lying)
        return jax.jit(lambda key: run_episode(env, recorded_policy, key, int(lying), params))(jax.random.key(3))

    outs = [episode(False), episode(True)]
    jax.effects_barrier()
    assert int(outs[0].length) == int(outs[1].length) > 20
    assert float(outs[0].iou) != float(outs[1].iou)  # the second world lied (its IoU sums are negative)
    np.testing.assert_array_equal(outs[0].team_return, outs[1].team_return)
    told = {t: v for (lying, t), v in log.items() if not lying}
    lied = {t: v for (lying, t), v in log.items() if lying}
    assert sorted(told) == sorted(lied) == list(range(int(outs[0].length)))
    for t in told:
        for a, b in zip(jax.tree.leaves(told[t]), jax.tree.leaves(lied[t]), strict=True):
            np.testing.assert_array_equal(a, b, err_msg=f"step {t}")
    actions = np.array([told[t][1] for t in told])
    assert len({tuple(a) for a in actions}) > 1 and np.any(actions == 4)  # it moves in several ways and builds


def test_the_check_catches_a_policy_that_reads_the_design():
    """A policy that keeps the design the evaluator hands its `init` (hidden on a static task) and
    shifts its observations by the design's mean: once the state lies, its actions differ."""
    agent, honest, shapes = _learner("ppo", "2d-static-sparse")

    def init(key, design):
        return {"inner": honest.init(key, design), "design": design.astype(jnp.float32)}

    def act(params, memory, obs, key):
        action, inner = honest.act(params, memory["inner"], obs + memory["design"].mean(), key)
        return action, {"inner": inner, "design": memory["design"]}

    log, acted_otherwise = {}, []
    run = _evaluator(agent, Policy(init, act, None, "cheat"), log)
    for seed in range(DRAWS):
        out = run(_random_params(shapes, seed))
        told, lied = ([log[(lying, t)][1] for t in range(int(np.min(out.length)))] for lying in (False, True))
        acted_otherwise.append(not np.array_equal(told, lied))
        with pytest.raises(AssertionError, match="differ"):
            _compare(log, out)
    assert any(acted_otherwise), acted_otherwise  # not only its memory (which holds the design) gives it away

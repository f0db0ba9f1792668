"""IPPO: PPO with one set of parameters shared by every robot of a team (SPEC §13), trained
end-to-end inside `jit`, as JaxMARL's IPPO baseline.

Each robot acts on its own observation with the robot's index appended one-hot, so one network
can still act differently per robot (who starts in which corner). Robots x worlds are stacked into
one batch for the network; every robot gets the team's reward (the env gives each robot the sum),
and a world auto-resets when its episode ends for all (`dones["__all__"]`).

`IPPO(config)` holds the static pieces; its methods are pure:

- `init(key) -> RunnerState` for one seed (every leaf under `worlds` has the world axis first);
- `rollout(state, env_params) -> (state, batch, stats)`: `rollout_steps` steps in every world;
- `update(state, env_params) -> (state, metrics)`: one rollout, then `update_epochs` passes over
  `num_minibatches` minibatches of worlds (each with all its robots);
- `train_chunk(state, env_params, n)`: `n` updates in a `lax.scan` (the driver runs chunks);
- `policy(params) -> snac_jax.multi.MultiPolicy`: the greedy team policy;
- `evaluate_team(params, ...) -> snac_jax.evaluation.TaskResult`: the protocol's episodes, run by the team.

`make_train(config)` returns the whole run as a pure `train(key)`. The module forks alone: besides
`snac_jax` it reads only the library modules `agents.training.config`, `agents.common.inputs`, `agents.common.networks`
and `agents.common.targets`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from agents.common.inputs import ObsLayout
from agents.common.networks import (
    ObservationEncoder,
    ScannedRNN,
    apply_with_design_cache,
    first_design_cache,
    mlp_head,
)
from agents.common.targets import gae, truncation_values
from agents.training.config import TrainConfig, option
from snac_jax import multi
from snac_jax.multi.rules import max_robots


@dataclasses.dataclass(frozen=True)
class IPPOConfig(TrainConfig):
    """IPPO on `robots` robots per world. `num_envs` counts worlds and `total_steps` env steps
    (one step of a whole team), so an update is `num_envs x rollout_steps` env steps and `robots`
    times as many robot-steps."""

    algorithm: ClassVar[str] = "ippo"
    paper_method: ClassVar[str] = "ippo"  # no paper row: the paper has one robot

    robots: int = option(2, "robots per world (snac_jax.multi, SPEC §13)", low=1, high=4)
    recurrent: bool = option(True, "GRU actor-critic instead of a feed-forward one")
    total_steps: int = option(30_000_000, "env steps (team steps) per seed; robot-steps are `robots` times this", low=1)
    num_envs: int = option(512, "parallel worlds per seed (split over devices)", low=1)
    rollout_steps: int = option(64, "steps per world between updates", low=1)
    update_epochs: int = option(2, "passes over each rollout", low=1)
    num_minibatches: int = option(2, "minibatches per pass; they split the worlds, each with all its robots", low=1)
    learning_rate: float = option(1e-3, "Adam step size", low=0, low_open=True)
    anneal_lr: bool = option(True, "decay the learning rate linearly to 0 over the run")
    gamma: float = option(0.99, "discount", low=0, high=1)
    gae_lambda: float = option(0.95, "GAE lambda", low=0, high=1)
    clip_eps: float = option(0.2, "PPO clip range of the ratio and the value", low=0, low_open=True)
    ent_coef: float = option(0.01, "entropy coefficient", low=0)
    vf_coef: float = option(0.5, "value loss weight", low=0)
    max_grad_norm: float = option(0.5, "global gradient norm clip", low=0, low_open=True)
    hidden_size: int = option(64, "width of the encoder and the heads", low=1)
    rnn_size: int = option(32, "GRU units (recurrent only)", low=1)
    reward_scale: float = option(
        0.01, "rewards are multiplied by this for learning (not for reporting)", low=0, low_open=True
    )

    def check(self) -> None:
        from snac_jax.tasks import parse_switches, task_spec

        high = max_robots(task_spec(self.task).dim)
        if not 1 <= self.robots <= high:
            raise ValueError(f"robots must be an int in 1..{high} for {self.task}, got {self.robots}")
        single = sorted({"landmark_action", "design_change"} & set(parse_switches(self.switches)))
        if single:
            raise ValueError(f"{single[0]} is a single-robot switch (SPEC §14-15); ippo trains snac_jax.multi worlds")
        if self.num_envs % self.num_minibatches:
            raise ValueError(
                f"num_envs ({self.num_envs}) must be a multiple of num_minibatches ({self.num_minibatches}): "
                "minibatches split the worlds"
            )

    def make_env(self):
        """The team's training environment `(MultiSNACEnv, params)`."""
        env = multi.make(self.task, num_robots=self.robots, **self.training_overrides)
        return env, env.default_params


class TeamActorCritic(nn.Module):
    """`ActorCritic` whose input ends with the robot's index one-hot (`num_robots` entries): the
    observation is encoded as for one robot, then the index joins the features the GRU and the
    heads read."""

    layout: ObsLayout
    num_actions: int
    num_robots: int
    hidden_size: int = 64
    rnn_size: int = 0  # 0: feed-forward

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.rnn_size or 1), jnp.float32)  # a (B, 1) placeholder for feed-forward

    @nn.compact
    def __call__(self, carry: jax.Array, inputs: jax.Array, resets: jax.Array):
        """`carry (B, C)`, `inputs (T, B, O + num_robots)`, `resets (T, B)` -> `(carry, logits, value)`."""
        x = ObservationEncoder(self.layout, self.hidden_size)(inputs[..., : -self.num_robots])
        x = jnp.concatenate([x, inputs[..., -self.num_robots :]], axis=-1)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        logits = mlp_head(x, self.hidden_size, self.num_actions, 0.01)
        value = mlp_head(x, self.hidden_size, 1, 1.0)[..., 0]
        return carry, logits, value


@struct.dataclass
class Worlds:
    """Everything with one entry per parallel world (axis 0, the axis the driver shards)."""

    env_state: Any  # MultiState
    obs: jax.Array  # (W, N, O), each robot's observation the next action sees
    previous_obs: jax.Array  # (W, N, O), the observations before them (ignored where `reset`)
    last_action: jax.Array  # (W, N) int32, the actions that led to `obs` (ignored where `reset`)
    reset: jax.Array  # (W,) bool, True where `obs` starts an episode (resets the GRU carries)
    carry: jax.Array  # (W, N, C) recurrent states (a placeholder for feed-forward)
    episode_return: jax.Array  # (W,) team return of the running episode so far


@struct.dataclass
class RunnerState:
    params: Any
    opt_state: Any
    worlds: Worlds
    key: jax.Array
    update: jax.Array  # int32, updates done


class Transition(NamedTuple):
    inputs: jax.Array  # (W, N, I) what the network read
    reset: jax.Array  # (W,)
    action: jax.Array  # (W, N)
    log_prob: jax.Array  # (W, N)
    value: jax.Array  # (W, N)
    reward: jax.Array  # (W,) the team reward
    terminated: jax.Array  # (W,)
    done: jax.Array  # (W,)
    final_inputs: jax.Array  # (W, N, I) the episode's last observations where `done`
    carry_after: jax.Array  # (W, N, C) carries after `inputs`: they score `final_inputs`


def team_objective(
    logits,
    value,
    action,
    old_log_prob,
    old_value,
    advantages,
    targets,
    clip_eps: float,
    vf_coef: float,
    ent_coef: float,
):
    """PPO's loss over every robot-step of a minibatch (all arrays of one shape, `logits` with
    the actions last): the clipped surrogate on normalised advantages, the clipped value loss and
    the entropy bonus; returns `(loss, info)`."""
    pi = distrax.Categorical(logits=logits)
    ratio = jnp.exp(pi.log_prob(action) - old_log_prob)
    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    actor_loss = -jnp.minimum(ratio * advantages, jnp.clip(ratio, 1 - clip_eps, 1 + clip_eps) * advantages).mean()
    clipped_value = old_value + jnp.clip(value - old_value, -clip_eps, clip_eps)
    value_loss = 0.5 * jnp.maximum((value - targets) ** 2, (clipped_value - targets) ** 2).mean()
    entropy = pi.entropy().mean()
    total = actor_loss + vf_coef * value_loss - ent_coef * entropy
    approx_kl = ((ratio - 1) - jnp.log(ratio)).mean()
    return total, {
        "loss": total,
        "value_loss": value_loss,
        "actor_loss": actor_loss,
        "entropy": entropy,
        "approx_kl": approx_kl,
    }


class IPPO:
    """Static pieces of an IPPO run; see the module docstring."""

    def __init__(self, config: IPPOConfig):
        config.validate()
        self.config = config
        # Not `self.env`: the single-robot tools that look for one (memory checks, the
        # single-robot evaluator) cannot run a team.
        self.team_env, self.env_params = config.make_env()
        self.robots = config.robots
        self.layout = ObsLayout.from_env(
            self.team_env.single, self.env_params, previous_step=config.previous_step, robots=self.robots
        )
        self.network = TeamActorCritic(
            layout=self.layout,
            num_actions=self.team_env.num_actions,
            num_robots=self.robots,
            hidden_size=config.hidden_size,
            rnn_size=config.rnn_size if config.recurrent else 0,
        )
        steps = config.num_updates * config.update_epochs * config.num_minibatches
        lr = optax.linear_schedule(config.learning_rate, 0.0, steps) if config.anneal_lr else config.learning_rate
        self.optimizer = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(lr, eps=1e-5))
        self._team = None  # the team policy's init and act, built once: the evaluation compiles once per learner

    # --- batches of robots ----------------------------------------------------------------------

    def _inputs(self, obs, previous_obs, last_action, reset) -> jax.Array:
        """`(..., N, I)`: each robot's network input, its index one-hot last."""
        reset = jnp.broadcast_to(reset[..., None], last_action.shape)
        x = self.layout.with_previous_step(obs, previous_obs, last_action, reset)
        index = jnp.broadcast_to(jnp.eye(self.robots, dtype=x.dtype), x.shape[:-1] + (self.robots,))
        return jnp.concatenate([x, index], axis=-1)

    @staticmethod
    def _robots_as_worlds(carry, inputs, resets):
        """`carry (W, N, C)`, `inputs (T, W, N, I)`, `resets (T, W)` as one batch of W * N."""
        t, w, n = inputs.shape[:3]
        resets = jnp.broadcast_to(resets[..., None], (t, w, n)).reshape(t, w * n)
        return carry.reshape(w * n, -1), inputs.reshape(t, w * n, -1), resets

    def _apply(self, params, carry, inputs, resets, design_cache=None):
        """The network on `carry (W, N, C)`, `inputs (T, W, N, I)`, `resets (T, W)`, robots x
        worlds as one batch; returns `(carry (W, N, C), logits (T, W, N, A), value (T, W, N))`,
        and the new design cache where one is given (acting: `apply_with_design_cache`)."""
        t, w, n = inputs.shape[:3]
        flat = self._robots_as_worlds(carry, inputs, resets)
        if design_cache is None:
            carry, logits, value = self.network.apply(params, *flat)
        else:
            (carry, logits, value), design_cache = apply_with_design_cache(self.network, params, design_cache, *flat)
        out = carry.reshape(w, n, -1), logits.reshape(t, w, n, -1), value.reshape(t, w, n)
        return out if design_cache is None else (out, design_cache)

    def _world_step(self, key, env_state, actions, env_params):
        env = self.team_env
        obs, env_state, rewards, dones, infos = env.step(
            key, env_state, {name: actions[i] for i, name in enumerate(env.agents)}, env_params
        )
        stack = lambda by_agent: jnp.stack([by_agent[name] for name in env.agents])
        return (
            stack(obs),
            env_state,
            rewards[env.agents[0]],
            dones["__all__"],
            infos["terminated"],
            infos["final_iou"],
            stack(infos["final_observation"]),
        )

    # --- pure functions -------------------------------------------------------------------------

    def init(self, key: jax.Array) -> RunnerState:
        w, n = self.config.num_envs, self.robots
        key, key_params, key_reset = jax.random.split(key, 3)
        obs, env_state = jax.vmap(self.team_env.reset, in_axes=(0, None))(
            jax.random.split(key_reset, w), self.env_params
        )
        obs = jnp.stack([obs[name] for name in self.team_env.agents], axis=1)
        worlds = Worlds(
            env_state=env_state,
            obs=obs,
            previous_obs=obs,
            last_action=jnp.zeros((w, n), jnp.int32),
            reset=jnp.ones((w,), bool),
            carry=self.network.initial_carry(w * n).reshape(w, n, -1),
            episode_return=jnp.zeros((w,), jnp.float32),
        )
        inputs = self._network_inputs(worlds).reshape(1, w * n, -1)[:, :1]
        params = self.network.init(key_params, self.network.initial_carry(1), inputs, jnp.ones((1, 1), bool))
        return RunnerState(
            params=params,
            opt_state=self.optimizer.init(params),
            worlds=worlds,
            key=key,
            update=jnp.zeros((), jnp.int32),
        )

    def _network_inputs(self, worlds: Worlds) -> jax.Array:
        return self._inputs(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)

    def rollout(self, state: RunnerState, env_params) -> tuple[RunnerState, Transition, dict]:
        w = self.config.num_envs
        step = jax.vmap(self._world_step, in_axes=(0, 0, 0, None))

        def env_step(carry, _):
            worlds, design_cache, key = carry
            key, key_act, key_step = jax.random.split(key, 3)
            inputs = self._network_inputs(worlds)
            (new_carry, logits, value), design_cache = self._apply(
                state.params, worlds.carry, inputs[None], worlds.reset[None], design_cache
            )
            pi = distrax.Categorical(logits=logits[0])
            action = pi.sample(seed=key_act)
            obs, env_state, reward, done, terminated, final_iou, final_obs = step(
                jax.random.split(key_step, w), worlds.env_state, action, env_params
            )
            episode_return = worlds.episode_return + reward
            no_reset = jnp.zeros_like(done)
            transition = Transition(
                inputs=inputs,
                reset=worlds.reset,
                action=action,
                log_prob=pi.log_prob(action),
                value=value[0],
                reward=reward,
                terminated=terminated,
                done=done,
                final_inputs=self._inputs(final_obs, worlds.obs, action, no_reset),
                carry_after=new_carry,
            )
            stats = {  # one episode per world, however many robots it has
                "episodes": done.sum(),
                "iou_sum": jnp.where(done, final_iou, 0.0).sum(),
                "return_sum": jnp.where(done, episode_return, 0.0).sum(),
            }
            worlds = Worlds(
                env_state=env_state,
                obs=obs,
                previous_obs=worlds.obs,
                last_action=action.astype(jnp.int32),
                reset=done,
                carry=new_carry,
                episode_return=jnp.where(done, 0.0, episode_return),
            )
            return (worlds, design_cache, key), (transition, stats)

        worlds = state.worlds
        first = self._robots_as_worlds(worlds.carry, self._network_inputs(worlds)[None], worlds.reset[None])
        design_cache = first_design_cache(self.network, state.params, *first)
        (worlds, _, key), (batch, stats) = jax.lax.scan(
            env_step, (worlds, design_cache, state.key), None, length=self.config.rollout_steps
        )
        return state.replace(worlds=worlds, key=key), batch, jax.tree.map(jnp.sum, stats)

    def _advantages(self, params, batch: Transition, worlds: Worlds) -> tuple[jax.Array, jax.Array]:
        """GAE advantages and value targets `(T, W, N)`: each robot's own value of the team reward.
        A truncated episode bootstraps from its final observations' values."""
        cfg = self.config
        t, w, n = batch.value.shape
        _, _, last_value = self._apply(params, worlds.carry, self._network_inputs(worlds)[None], worlds.reset[None])
        per_robot = lambda x: jnp.broadcast_to(x[..., None], (t, w, n)).reshape(t, w * n)
        flat = lambda x: x.reshape((t, w * n) + x.shape[3:])
        done, terminated = per_robot(batch.done), per_robot(batch.terminated)

        def score(carry, inputs):
            _, _, value = self.network.apply(params, carry, inputs[None], jnp.zeros((1, inputs.shape[0]), bool))
            return value[0]

        following = jnp.concatenate([flat(batch.value)[1:], last_value.reshape(1, w * n)], axis=0)
        next_values = jnp.where(
            done,
            truncation_values(
                score,
                done & ~terminated,
                flat(batch.final_inputs),
                flat(batch.carry_after),
                self.layout.max_truncations(t),
            ),
            following,
        )
        advantages, targets = gae(
            per_robot(batch.reward) * cfg.reward_scale,
            flat(batch.value),
            next_values,
            terminated.astype(jnp.float32),
            done,
            cfg.gamma,
            cfg.gae_lambda,
        )
        return advantages.reshape(t, w, n), targets.reshape(t, w, n)

    def _loss(self, params, carry0, batch: Transition, advantages, targets):
        cfg = self.config
        _, logits, value = self._apply(params, carry0, batch.inputs, batch.reset)
        return team_objective(
            logits,
            value,
            batch.action,
            batch.log_prob,
            batch.value,
            advantages,
            targets,
            cfg.clip_eps,
            cfg.vf_coef,
            cfg.ent_coef,
        )

    def update(self, state: RunnerState, env_params) -> tuple[RunnerState, dict[str, jax.Array]]:
        cfg = self.config
        carry0 = state.worlds.carry
        state, batch, stats = self.rollout(state, env_params)
        advantages, targets = self._advantages(state.params, batch, state.worlds)
        batch = batch._replace(final_inputs=None, carry_after=None)
        grad_fn = jax.value_and_grad(self._loss, has_aux=True)
        m = cfg.num_minibatches

        def epoch(carry, _):
            params, opt_state, key = carry
            key, key_perm = jax.random.split(key)
            perm = jax.random.permutation(key_perm, cfg.num_envs)

            def split(x, axis):  # shuffle the worlds, then cut them into m minibatches
                x = jnp.take(x, perm, axis=axis)
                return jnp.moveaxis(x.reshape(x.shape[:axis] + (m, -1) + x.shape[axis + 1 :]), axis, 0)

            minibatches = (
                split(carry0, 0),
                jax.tree.map(lambda x: split(x, 1), batch),
                split(advantages, 1),
                split(targets, 1),
            )

            def minibatch_step(carry, minibatch):
                params, opt_state = carry
                (_, info), grads = grad_fn(params, *minibatch)
                updates, opt_state = self.optimizer.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), info

            (params, opt_state), info = jax.lax.scan(minibatch_step, (params, opt_state), minibatches)
            return (params, opt_state, key), info

        (params, opt_state, key), info = jax.lax.scan(
            epoch, (state.params, state.opt_state, state.key), None, length=cfg.update_epochs
        )
        return (
            state.replace(params=params, opt_state=opt_state, key=key, update=state.update + 1),
            {**jax.tree.map(jnp.mean, info), **stats},
        )

    def train_chunk(self, state: RunnerState, env_params, num_updates: int) -> tuple[RunnerState, dict]:
        """`num_updates` updates; metrics stacked along a leading axis of that length."""
        return jax.lax.scan(lambda s, _: self.update(s, env_params), state, None, length=num_updates)

    # --- acting ---------------------------------------------------------------------------------

    def policy(self, params) -> multi.MultiPolicy:
        """The trained network as the greedy team policy: every robot argmaxes its own logits."""
        n = self.robots

        def init(key, design):
            return {
                "carry": self.network.initial_carry(n),
                "reset": jnp.ones((), bool),
                "previous_obs": jnp.zeros((n, self.layout.env_obs_size), jnp.float32),
                "last_action": jnp.zeros((n,), jnp.int32),
            }

        def act(params, memory, obs, key):
            inputs = self._inputs(obs, memory["previous_obs"], memory["last_action"], memory["reset"])
            carry, logits, _ = self._apply(
                params, memory["carry"][None], inputs[None, None], memory["reset"][None, None]
            )
            actions = jnp.argmax(logits[0, 0], axis=-1).astype(jnp.int32)
            return actions, {
                "carry": carry[0],
                "reset": jnp.zeros((), bool),
                "previous_obs": obs.astype(jnp.float32),
                "last_action": actions,
            }

        kind = "recurrent" if self.config.recurrent else "feed-forward"
        return multi.MultiPolicy(init, act, params, f"ippo-{kind}-{n}-robots")

    def evaluate_team(self, params, *, static_episodes: int, episodes_per_test_design: int, seed: int):
        """The protocol (SPEC §8) run by the team, `snac_jax.multi.evaluate_team_task` (the one
        `snac eval --robots` and `--checkpoint` run): the evaluator's `TaskResult`."""
        if self._team is None:
            self._team = self.policy(None)
        team = self._team._replace(params=params)
        return multi.evaluate_team_task(
            self.config.task,
            team,
            self.config.robots,
            static_episodes=static_episodes,
            episodes_per_test_design=episodes_per_test_design,
            seed=seed,
            **self.config.env_overrides,
        ).result


def make_train(config: IPPOConfig):
    """The whole run as a pure function of a key: `jax.jit(jax.vmap(make_train(c)))(keys)`."""
    ippo = IPPO(config)

    def train(key: jax.Array) -> tuple[RunnerState, dict[str, jax.Array]]:
        return ippo.train_chunk(ippo.init(key), ippo.env_params, ippo.config.num_updates)

    return train

"""`SNACEnv`: the SNAC tasks as one gymnax environment class, configured by an `EnvConfig`."""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnax.environments import environment, spaces

from snac_jax import batched_step, design_change, landmark_action, metrics, observation, threefry
from snac_jax.config import MAX_STRIDE, EnvConfig
from snac_jax.state import EnvParams, EnvState, PrivilegedState
from snac_jax.transition import PADDING, is_stuck, transition


def random_words(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Two independent uint32 words from one hash of `key`: `key_data(fold_in(key, 0))`.

    A step needs a stride and, for the auto-reset, a design index: one Threefry block gives
    both. (`jax.random.split` followed by a draw costs three blocks or more per env per step,
    and on the CPU `snac_jax.threefry` computes the block fused with the rest of the step.)
    """
    return threefry.fold_in_words(key)


def unit_float(word: jax.Array) -> jax.Array:
    """A uniform float32 in [0, 1) from the 23 high bits of a uint32 word (as `jax.random.uniform`)."""
    mantissa = jax.lax.shift_right_logical(word, jnp.uint32(9)) | jnp.uint32(0x3F800000)
    return jax.lax.bitcast_convert_type(mantissa, jnp.float32) - 1.0


def draw_stride(word: jax.Array, stride_probs: jax.Array) -> jax.Array:
    """d in {1, 2, 3} with probabilities `stride_probs`, from one random uint32 word."""
    u = unit_float(word)
    cumulative = jnp.cumsum(stride_probs)
    return (1 + (u >= cumulative[0]) + (u >= cumulative[1])).astype(jnp.int32)


def draw_design_index(word: jax.Array, num_designs: int) -> jax.Array:
    """An index into a bank of `num_designs` designs from one random uint32 word.

    `word % K` is exactly uniform when K is a power of two (the default bank has 16384
    designs) and biased by at most K / 2**32 otherwise.
    """
    if num_designs == 1:
        return jnp.zeros((), jnp.int32)
    return (word % jnp.uint32(num_designs)).astype(jnp.int32)


def _host_values(x: Any) -> np.ndarray | None:
    """`x` as a NumPy array when its value is known while tracing (a Python or NumPy number, a
    concrete array), else None: a traced value is checked by nobody (see `SNACEnv.step`)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)


def check_range(name: str, x: Any, low: int, high: int) -> None:
    """`ValueError` if a known value of `x` lies outside low..high (traced values pass)."""
    values = _host_values(x)
    if values is not None and values.size and (values.min() < low or values.max() > high):
        bad = values[(values < low) | (values > high)].reshape(-1)[0]
        raise ValueError(f"{name} must be in {low}..{high}, got {bad}")


def _shown(x: Any) -> str:
    """How an argument that should have been one int appears in an error message."""
    if isinstance(x, jax.core.Tracer):
        return f"a traced {x.dtype}{list(x.shape)} value"
    values = np.asarray(x)
    return repr(values.item()) if values.ndim == 0 else f"an {values.dtype} array of shape {values.shape}"


def check_integer(name: str, x: Any, low: int, high: int) -> None:
    """`ValueError` unless `x` is one integer (any integer dtype, bool excluded) and, when its value
    is known, in low..high; a traced integer's value passes unchecked (see `SNACEnv.step`).

    Why: a float, a bool or an array where one index belongs would otherwise fail deep inside
    JAX without naming the argument (or, a bool, index as a mask). Dtypes and shapes are static,
    so this holds for traced values too and costs nothing per step."""
    dtype = x.dtype if isinstance(x, jax.core.Tracer) else np.asarray(x).dtype
    if np.shape(x) != () or not np.issubdtype(dtype, np.integer):
        raise ValueError(f"{name} must be one int in {low}..{high}, got {_shown(x)}")
    check_range(name, x, low, high)


class SNACEnv(environment.Environment[EnvState, EnvParams]):
    """One SNAC task. Build it with `snac_jax.make(task_id, **overrides)`.

    Equal configurations hash equal, so gymnax's jitted `step`/`reset` (static on `self`)
    compile once per configuration, not once per instance.
    """

    def __init__(self, config: EnvConfig, default_params: EnvParams):
        super().__init__()
        self.config = config
        self._default_params = default_params

    def __hash__(self) -> int:
        return hash(self.config)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SNACEnv) and other.config == self.config

    def __repr__(self) -> str:
        return f"SNACEnv({self.config.task_id!r})"

    @property
    def name(self) -> str:
        return self.config.task_id

    @property
    def default_params(self) -> EnvParams:
        return self._default_params

    @property
    def num_actions(self) -> int:
        return self.config.num_actions

    # --- input checks --------------------------------------------------------------------------
    # Shapes are static, so these run once while tracing and cost nothing per step.

    def check_params(self, params: EnvParams) -> None:
        """`ValueError` unless `params` have the shapes of this task's (another task's params would
        otherwise run: JAX pads and clamps what does not fit)."""
        k = params.designs.shape[0] if params.designs.ndim else 0
        expected = {
            "designs": (k, *self.config.plan_shape),
            "design_max_bricks": (k,),
            "design_volume": (k,),
            "stride_probs": (MAX_STRIDE,),
        }
        for name, shape in expected.items():
            got = tuple(getattr(params, name).shape)
            if got != shape:
                raise ValueError(
                    f"params.{name} has shape {got}, {self!r} needs {shape}: params of another task? "
                    "(snac_jax.make builds the matching pair)"
                )

    def check_state(self, state: EnvState) -> None:
        """`ValueError` unless `state` has this task's grid and design shapes."""
        for name, shape in (("grid", self.config.grid_shape), ("design", self.config.plan_shape)):
            got = tuple(getattr(state, name).shape)
            if got != shape:
                raise ValueError(f"state.{name} has shape {got}, {self!r} needs {shape}: a state of another task?")

    # --- reset ---------------------------------------------------------------------------------

    def _empty_grid(self) -> np.ndarray:
        (pr, pc), (h, w) = self.config.pad, self.config.plan_shape
        grid = np.full(self.config.grid_shape, PADDING, dtype=self.config.grid_dtype)
        grid[pr : pr + h, pc : pc + w] = 0
        return grid

    def _place_landmarks(self, key: jax.Array, design: jax.Array) -> jax.Array:
        """K distinct landmark cells, uniform over the plan cells outside the design."""
        scores = jax.random.gumbel(key, design.shape)
        scores = jnp.where(design > 0, -jnp.inf, scores).reshape(-1)
        _, chosen = jax.lax.top_k(scores, self.config.num_landmarks)
        plan_mask = jnp.zeros(design.size, dtype=bool).at[chosen].set(True).reshape(design.shape)
        (pr, pc) = self.config.pad
        return jnp.pad(plan_mask, ((pr, pr), (pc, pc)))

    def reset_to_design(self, key: jax.Array, params: EnvParams, design_index: jax.Array) -> tuple[jax.Array, EnvState]:
        """Reset onto `params.designs[design_index]` (the evaluator pins test designs this way).

        `design_index` must be one int in 0..K-1 for the K designs of `params`: a known index
        outside, or anything but one integer, is a `ValueError`; a traced integer's value is not
        checked (JAX would clamp it to the bank).
        """
        self.check_params(params)
        check_integer("design_index", design_index, 0, params.designs.shape[0] - 1)
        design = params.designs[design_index]
        landmarks = None
        if self.config.num_landmarks:
            landmarks = self._place_landmarks(key, design)
        switched = {}  # SPEC §14-15: fields only the two switches add
        if self.config.landmark_action:
            switched.update(landmark_action.reset_fields(self.config, landmarks))
        if self.config.design_change is not None:
            switched.update(design_change.reset_fields(self.config, key, params, design_index))
        state = EnvState(
            grid=jnp.asarray(self._empty_grid()),
            position=jnp.zeros(2, dtype=jnp.int32),
            design=design,
            max_bricks=params.design_max_bricks[design_index],
            bricks_used=jnp.zeros((), jnp.int32),
            time=jnp.zeros((), jnp.int32),
            overlap=jnp.zeros((), jnp.int32),
            union=params.design_volume[design_index],
            landmarks=landmarks,
        ).replace(**switched)
        return self.get_obs(state, params), state

    def reset_env(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """A fresh episode on a design drawn from `params.designs`.

        The design index comes from the second word of `random_words(key)`; `step_env` draws the
        stride from the first. So the auto-reset in `step`, which hands both the same key, costs
        one hash per env per step (XLA merges the identical hashes).
        """
        index = draw_design_index(random_words(key)[1], params.designs.shape[0])
        key_landmarks = jax.random.fold_in(key, 1) if self.config.num_landmarks else key
        return self.reset_to_design(key_landmarks, params, index)

    # --- step ----------------------------------------------------------------------------------

    @partial(jax.jit, static_argnames=("self",))
    def step(
        self, key: jax.Array, state: EnvState, action: int | jax.Array, params: EnvParams | None = None
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        """gymnax's auto-resetting step, with the same outputs and info keys, made cheaper.

        `action` must be in 0..num_actions-1. It is not checked here (a check on a traced value
        would cost every step): JAX's gather clamps an index outside the action table, so 99 acts
        as the last action, and a negative one counts from the end first (-1 is the last, -100
        clamps to 0). `snac_jax.evaluation` counts such actions and refuses to score a policy
        that takes them. The shapes of `state` and `params` are checked while tracing.

        - One hash of `key` per step: `step_env` and `reset_env` read different words of it.
        - The observation is computed once, of the state after the auto-reset, instead of for
          both the stepped and the reset state (`final_observation`, the stepped state's
          observation, costs nothing unless it is used).
        - A static task's reset state does not depend on the key, so under `vmap` it stays
          unbatched and the auto-reset is a broadcast select.
        """
        return self.step_keeping_final_state(key, state, action, params)[:6]

    @partial(jax.jit, static_argnames=("self",))
    def step_keeping_final_state(
        self, key: jax.Array, state: EnvState, action: int | jax.Array, params: EnvParams | None = None
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any], EnvState]:
        """`step`'s six outputs, then the state the step reached before the auto-reset replaced it.

        Why: training signals that read the world's truth (`privileged`, hindsight relabelling)
        need an ending episode's last state, which `step` discards. Inside a larger `jit` an
        unused seventh output costs nothing.
        """
        if params is None:
            params = self.default_params
        _, state_stepped, reward, terminated, info = self.step_env(key, state, action, params)
        truncated = self.is_truncated(state_stepped, params)
        done = terminated | truncated
        _, state_reset = self.reset_env(key, params)
        state = jax.tree.map(lambda r, s: jnp.where(done, r, s), state_reset, state_stepped)
        info = {
            **info,
            "terminated": terminated,
            "truncated": truncated,
            "final_observation": self.get_obs(state_stepped, params),
        }
        return self.get_obs(state, params), state, reward, terminated, truncated, info, state_stepped

    def step_batch(
        self,
        keys: jax.Array,
        states: EnvState,
        actions: jax.Array,
        params: EnvParams | None = None,
        reset: str = "auto",
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        """`jax.vmap(env.step, in_axes=(0, 0, 0, None))` bit for bit, with the auto-reset computed
        the way that suits the backend: `reset` is `"loop"` (reset the ended worlds one by one:
        fast on a CPU), `"select"` (compute every world's fresh state and select, as gymnax: fast
        on a GPU or TPU) or `"auto"` (loop on a CPU, select elsewhere). `snac_jax.batched_step`
        says why; anything else is a `ValueError` naming the strategies."""
        return self._step_batch(keys, states, actions, params, batched_step.resolve_reset(reset))

    @partial(jax.jit, static_argnames=("self", "reset"))
    def _step_batch(
        self, keys: jax.Array, states: EnvState, actions: jax.Array, params: EnvParams | None, reset: str
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        if params is None:
            params = self.default_params
        return batched_step.step_batch(self, keys, states, actions, params, reset)

    def step_env(
        self, key: jax.Array, state: EnvState, action: int | jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        stride = draw_stride(random_words(key)[0], params.stride_probs)
        return self.step_with_stride(state, action, stride, params)

    def step_with_stride(
        self, state: EnvState, action: int | jax.Array, stride: int | jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        """The deterministic step for a given stride, without auto-reset (replays use it).

        `info["final_iou"]` is the IoU after this step: the episode's final IoU on the step
        that ends it (terminated or truncated). `stride` must be one int in 1..3 and `action` one
        in 0..num_actions-1: known values outside, and anything but one integer, are a
        `ValueError`; a traced integer's value is not checked (see `step`).
        """
        self.check_params(params)
        self.check_state(state)
        check_integer("action", action, 0, self.num_actions - 1)
        check_integer("stride", stride, 1, MAX_STRIDE)
        state, reward, terminated = transition(self.config, state, jnp.asarray(action), jnp.asarray(stride))
        info = {"final_iou": metrics.iou(state), "stride": jnp.asarray(stride, jnp.int32)}
        return self.get_obs(state, params), state, reward, terminated, info

    def privileged(self, state: EnvState, params: EnvParams | None = None) -> PrivilegedState:
        """The world's hidden truth for training signals only (SPEC §12): the true plan position,
        the bricks built on the plan, the design and whether the robot is stuck.

        Why: a learner may train its critic or auxiliary losses on what the robot cannot see
        (asymmetric actor-critic, localisation losses), while the policy it is scored with still
        reads only `step`'s observation. `step` and its observation are unchanged; vmap this over
        a batch of states as `step` is (a batch itself is refused: its slices would cut the
        batch axis, not the plan).
        """
        grid, one = tuple(state.grid.shape), self.config.grid_shape
        if len(grid) > len(one) and grid[-len(one) :] == one:
            raise ValueError(
                f"env.privileged takes one world's state, got a batch of shape {grid[: -len(one)]}: "
                "jax.vmap(env.privileged, in_axes=(0, None))(states, params)"
            )
        self.check_state(state)
        (pr, pc), (h, w) = self.config.pad, self.config.plan_shape
        return PrivilegedState(
            position=state.position.astype(jnp.int32),
            built=state.grid[pr : pr + h, pc : pc + w],
            design=state.design,
            stuck=is_stuck(self.config, state),
        )

    @property
    def observation_layout(self) -> observation.ObservationLayout:
        """Where the window, counters, design and position sit in the flat observation."""
        return observation.layout(self.config)

    def get_obs(self, state: EnvState, params: EnvParams | None = None, key: jax.Array | None = None) -> jax.Array:
        return observation.observe(self.config, state)

    def is_terminated(self, state: EnvState, params: EnvParams) -> jax.Array:
        """Out of bricks, or (with obstacles) stuck: the conditions `transition` ends on."""
        return (state.bricks_used >= state.max_bricks) | is_stuck(self.config, state)

    def render(self, state: EnvState, params: EnvParams | None = None, **kwargs) -> np.ndarray:
        """An RGB picture of one (unbatched) state; see `snac_jax.rendering.render`."""
        from snac_jax.rendering import render  # rendering stays out of the step's imports

        return render(self, state, params or self.default_params, **kwargs)

    # --- spaces --------------------------------------------------------------------------------

    def action_space(self, params: EnvParams | None = None) -> spaces.Discrete:
        """The `num_actions` discrete actions; static, so it works under `jit` and `vmap`."""
        return spaces.Discrete(self.config.num_actions)

    def observation_low(self) -> np.ndarray:
        """The observation's per-entry lower bounds (see `observation_space`) as a NumPy array: they
        depend on the configuration only, never on `params`, so they stay concrete inside `jit`
        where a caller (the multi-robot env's space) edits them with NumPy."""
        config, layout = self.config, self.observation_layout
        marks = config.num_landmarks or config.landmark_action
        floor = observation.LANDMARK_VALUE if marks else float(PADDING)
        window_low = np.full(layout.window_shape, floor, np.float32)
        window_low[config.pad] = observation.LANDMARK_VALUE if marks else 0.0
        low = np.zeros(layout.size, np.float32)
        low[layout.window] = window_low.reshape(-1)
        return low

    def observation_space(self, params: EnvParams | None = None) -> spaces.Box:
        """Per-entry bounds of the flat observation, laid out as `observation_layout` says.

        - window cells: from -2 where landmarks can show (-1, the padding, otherwise; the centre
          cell is the robot's own plan cell and never padding) up to 1 on the binary 2D grid, else
          up to the most bricks an episode can drop, min(largest brick budget, step limit);
        - N_b in [0, min(largest brick budget, step limit)], N_s in [0, step limit];
        - design cells in [0, tallest design value]; the GPS position in [0, plan size - 1].

        `low` is static; `high` is computed from `params` with `jnp` only, so the space can be
        built inside `jit` and `vmap` with `params` traced (as gymnax's own environments allow).
        """
        if params is None:
            params = self.default_params
        config, layout = self.config, self.observation_layout
        low = self.observation_low()
        steps = jnp.asarray(params.max_steps_in_episode).astype(jnp.float32)
        bricks = jnp.minimum(jnp.max(params.design_max_bricks).astype(jnp.float32), steps)
        if config.design_change is not None:
            bricks = steps  # a change tops the budget up (SPEC §15): only the step limit bounds N_b
        high = jnp.zeros(layout.size, jnp.float32)
        high = high.at[layout.window].set(1.0 if config.binary_grid else bricks)
        high = high.at[layout.bricks_used].set(bricks)
        high = high.at[layout.time].set(steps)
        if layout.design is not None:
            high = high.at[layout.design].set(jnp.max(params.designs).astype(jnp.float32))
        if layout.position is not None:
            plan_high = np.asarray(config.plan_shape, np.float32) - 1
            high = high.at[layout.position].set(plan_high[-(layout.position.stop - layout.position.start) :])
        return spaces.Box(jnp.asarray(low), high, (layout.size,), jnp.float32)

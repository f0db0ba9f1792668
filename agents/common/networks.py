"""Network pieces shared by every learner: the observation and design encoders, a GRU or LSTM
scanned over time with resets at episode boundaries, and the actor-critic and Q heads. What they
read, and how it is scaled, is `agents.common.inputs.ObsLayout`.

Every network takes time-major inputs `(T, B, obs_size)` with `resets (T, B)` (True where the
observation starts a new episode) and a carry `(B, carry_size)`, and returns the new carry.
Feed-forward networks ignore the carry (a `(B, 1)` placeholder), so one training loop serves both.

Initialisers are variance-scaling ones, never orthogonal: orthogonal init inside a jit vmapped
over seeds deadlocked on 2 CPU cores.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from agents.common.inputs import ObsLayout
from agents.common.noisy import noisy_dense


def scaled_init(gain: float) -> nn.initializers.Initializer:
    """Fan-in scaled normal with the variance an orthogonal init of this gain would give."""
    return nn.initializers.variance_scaling(gain**2, "fan_in", "truncated_normal")


Layer = Callable[[int, float], nn.Module]  # (features, gain) -> a dense layer; networks build theirs through one


def dense(features: int, gain: float) -> nn.Module:
    return nn.Dense(features, kernel_init=scaled_init(gain))


class StridedConv(nn.Module):
    """`nn.Conv(features, (3, 3), strides=(2, 2), padding="SAME")` with the same parameters, computed
    as one matrix product over the input's 3x3 patches (cut out by strided slices).

    Why: inside the learners' update loops (`lax.scan` over epochs and minibatches) XLA's CPU
    convolution and its gradient take a slow path that the same call outside a loop does not,
    and the dynamic 2D and 3D tasks, whose design goes through the encoder, paid for it on every
    step (the timings are on bench/results/ppo.md). A matrix product has no such slow path."""

    features: int
    kernel: int = 3
    stride: int = 2

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, s = self.kernel, self.stride
        weight = self.param("kernel", scaled_init(np.sqrt(2)), (k, k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        out = [-(-size // s) for size in x.shape[1:3]]  # "SAME": ceil(size / stride)
        pads = [max((o - 1) * s + k - size, 0) for o, size in zip(out, x.shape[1:3])]
        x = jnp.pad(x, [(0, 0)] + [(p // 2, p - p // 2) for p in pads] + [(0, 0)])
        patches = jnp.stack(
            [
                x[:, i : i + (out[0] - 1) * s + 1 : s, j : j + (out[1] - 1) * s + 1 : s]
                for i in range(k)
                for j in range(k)
            ],
            axis=-2,
        )  # (N, H', W', k*k, C), the kernel's order
        return patches.reshape(patches.shape[:3] + (-1,)) @ weight.reshape(-1, self.features) + bias


class DesignEncoder(nn.Module):
    """Features of a dynamic task's design: a dense layer over a row of column heights, a small
    strided conv over a 2D/3D plan.

    Why dense in 1D: a 1D conv over the 30 columns made training much slower for no clear gain
    in score (bench/results/ppo.md)."""

    features: int

    @nn.compact
    def __call__(self, design: jax.Array) -> jax.Array:
        lead, plan = design.shape[:-2], design.shape[-2:]
        if plan[0] == 1:  # 1D: the row of column heights through a dense layer
            x = design.reshape((-1, plan[1]))
            x = nn.relu(nn.Dense(self.features, kernel_init=scaled_init(np.sqrt(2)))(x))
        else:
            x = design.reshape((-1,) + plan + (1,))
            x = nn.relu(StridedConv(16, name="Conv_0")(x))
            x = nn.relu(StridedConv(16, name="Conv_1")(x))
            x = x.reshape((x.shape[0], -1))
        x = nn.relu(nn.Dense(self.features, kernel_init=scaled_init(np.sqrt(2)))(x))
        return x.reshape(lead + (self.features,))


def encode_design_runs(encode: Callable[[jax.Array], jax.Array], designs: jax.Array, max_runs: int) -> jax.Array:
    """`encode` of time-major `designs (T, B, *plan)` -> `(T, B, F)`, calling `encode` on one
    design per run of equal designs in each column (at most `max_runs` runs) instead of on all T.

    Why: a dynamic task's design stays the same for a whole episode, and its encoder costs more
    than the rest of the network; run once per episode, a sequence of T steps pays for the few
    designs it holds. The gradient is the same sum over steps (float tolerance), gathered onto
    each run's one encoding. A column with more runs than `max_runs` (a wrong bound) reads NaN,
    so the loss, and the driver's divergence flag, say so rather than train on another design.
    """
    if max_runs >= designs.shape[0]:
        return encode(designs)
    starts, _ = _run_starts(designs)
    run = jnp.cumsum(starts, axis=0) - 1  # (T, B): the run each step belongs to
    first = jax.vmap(lambda s: jnp.nonzero(s, size=max_runs, fill_value=0)[0], in_axes=1, out_axes=1)(starts)
    run_designs = jnp.take_along_axis(designs, first.reshape(first.shape + (1,) * (designs.ndim - 2)), axis=0)
    features = encode(run_designs)  # (max_runs, B, F)
    out = jnp.take_along_axis(features, jnp.minimum(run, max_runs - 1)[..., None], axis=0)
    return jnp.where((run < max_runs)[..., None], out, jnp.nan)


def runs_in_a_loop() -> bool:
    """Whether a sequence's design runs are encoded by `encode_each_run` (a loop of passes until
    every run is encoded, exact whatever their number) rather than `encode_design_runs` (one
    pass over a static bound of runs per column). On a CPU a pass costs in proportion to its
    size and the bound is far above the usual count (22 runs per 64 steps in 3D, where a policy's
    episodes hold one or two), so the loop; on an accelerator a loop of passes is a serial chain
    of kernels, and one bounded pass costs little more than a small one."""
    return jax.default_backend() == "cpu"


def run_chunk(columns: int) -> int:
    """Runs `encode_each_run` encodes per pass: as many as the sequence has columns, so that the
    usual sequence (one run per column, some with a second where an episode ended inside it)
    takes two passes: fewer passes than a quarter of the columns each, which a learner with many
    minibatch steps an update (PPO's 16) pays for (`bench/design_runs_ab.py`, measured in
    bench/results/train_throughput.md)."""
    return columns


def _run_starts(designs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """For time-major `designs (T, B, *plan)`, both `(T, B)`: whether each step starts a run of
    one design in its column, and the entry of `designs` flattened to `T * B` that starts the
    run it belongs to."""
    steps, columns = designs.shape[:2]
    flat = designs.reshape(steps, columns, -1)
    changed = jnp.any(flat[1:] != flat[:-1], axis=-1)  # (T - 1, B)
    starts = jnp.concatenate([jnp.ones((1, columns), bool), changed], axis=0)
    first_step = jax.lax.cummax(jnp.where(starts, jnp.arange(steps)[:, None], 0), axis=0)
    return starts, first_step * columns + jnp.arange(columns)


def _over_run_starts(starts: jax.Array, chunk: int, body: Callable, init):
    """`body(index, carry)` over the run starts, `chunk` indices at a time, until none is left;
    an index past the end (`starts.size`) pads the last pass."""
    size = starts.shape[0]

    def one_pass(state):
        todo, carry = state
        index = jnp.nonzero(todo, size=chunk, fill_value=size)[0]
        return todo.at[index].set(False, mode="drop"), body(index, carry)

    return jax.lax.while_loop(lambda state: jnp.any(state[0]), one_pass, (starts, init))[1]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 3))
def encode_each_run(apply: Callable, params, designs: jax.Array, chunk: int) -> jax.Array:
    """`apply(params, designs (n, *plan)) -> (n, F)` of time-major `designs (T, B, *plan)` ->
    `(T, B, F)`, encoding each run of one design in a column once, `chunk` runs per pass of a
    loop that stops when none is left, so exact however many runs a sequence holds (`run_chunk`).

    Why a custom gradient: a loop whose trip count depends on the data has no reverse-mode
    derivative in JAX. The gradient is the per-step one summed over each run's steps (float
    tolerance), pulled back through `apply` once per run in a second loop of passes."""
    return _encode_each_run(apply, params, designs, chunk)[0]


def _encode_each_run(apply, params, designs, chunk):
    steps, columns = designs.shape[:2]
    flat = designs.reshape((steps * columns,) + designs.shape[2:])
    starts, owner = (x.reshape(-1) for x in _run_starts(designs))
    size = flat.shape[0]
    out = jax.eval_shape(apply, params, flat[:1])

    def encode(index, features):
        return features.at[index].set(apply(params, flat[jnp.minimum(index, size - 1)]), mode="drop")

    features = _over_run_starts(starts, chunk, encode, jnp.zeros((size,) + out.shape[1:], out.dtype))
    residuals = (params, designs, flat, starts, owner)  # the backward pass's runs, found once
    return features[owner].reshape((steps, columns) + out.shape[1:]), residuals


def _encode_each_run_backward(apply, chunk, residuals, cotangent):
    params, designs, flat, starts, owner = residuals
    size = flat.shape[0]
    per_run = jnp.zeros((size,) + cotangent.shape[2:], cotangent.dtype)
    per_run = per_run.at[owner].add(cotangent.reshape((size,) + cotangent.shape[2:]))

    def pull_back(index, grads):
        _, vjp = jax.vjp(lambda p: apply(p, flat[jnp.minimum(index, size - 1)]), params)
        (more,) = vjp(per_run.at[index].get(mode="fill", fill_value=0))  # padding: no cotangent
        return jax.tree.map(jnp.add, grads, more)

    grads = _over_run_starts(starts, chunk, pull_back, jax.tree.map(jnp.zeros_like, params))
    no_design_gradient = (
        jnp.zeros_like(designs)
        if jnp.issubdtype(designs.dtype, jnp.inexact)
        else np.zeros(designs.shape, jax.dtypes.float0)
    )
    return grads, no_design_gradient


encode_each_run.defvjp(_encode_each_run, _encode_each_run_backward)


def _apply_design_encoder(features: int, params, designs: jax.Array) -> jax.Array:
    """`DesignEncoder` features of `designs`, times `params["kernel"]` where one is given (the
    first hidden layer's rows for them: `ObservationEncoder.__call__`)."""
    encoded = DesignEncoder(features).apply({"params": params["encoder"]}, designs)
    return encoded if params["kernel"] is None else encoded @ params["kernel"]


DESIGN_CACHE = "design_cache"  # the flax collection of the last design each world showed, and its first-layer share


def design_refresh_chunk(worlds: int) -> int:
    """How many worlds' designs `refresh_design_features` encodes per pass. On a CPU a pass
    costs in proportion to its size, and few worlds start an episode on any one step, so a
    sixteenth of the batch; on an accelerator one pass over the whole batch costs little more
    than a small one, and a loop of passes would wait on the host each step, so the batch."""
    return max(1, -(-worlds // 16)) if jax.default_backend() == "cpu" else worlds


def refresh_design_features(
    encode: Callable[[jax.Array], jax.Array], designs: jax.Array, seen: jax.Array, features: jax.Array
) -> jax.Array:
    """`features (B, F)` of `designs (B, *plan)`, given the `features` of the designs `seen`
    last: `encode` runs only on the worlds whose design changed (a new episode, a design change;
    every world where `seen` is NaN), a chunk of `design_refresh_chunk(B)` of them per pass.

    Why: acting reads one step of every world, and a dynamic task's design is constant for an
    episode, so encoding it for every world at every step spent most of the acting time on
    designs already encoded. The loop is exact whatever the number of changed worlds."""
    worlds = designs.shape[0]
    chunk = design_refresh_chunk(worlds)
    changed = jnp.any((designs != seen).reshape(worlds, -1), axis=-1)
    if chunk >= worlds:
        return jnp.where(changed[:, None], encode(designs), features)

    def refresh(encode, carry):
        features, todo = carry
        index = jnp.nonzero(todo, size=chunk, fill_value=worlds)[0]  # `worlds`: past the end, dropped
        fresh = encode(designs[jnp.minimum(index, worlds - 1)])
        return features.at[index].set(fresh, mode="drop"), todo.at[index].set(False, mode="drop")

    pending = lambda encode, carry: jnp.any(carry[1])
    if isinstance(encode, nn.Module):  # a bound submodule: flax's lifted loop
        features, _ = nn.while_loop(pending, refresh, encode, (features, changed))
    else:
        features, _ = jax.lax.while_loop(
            lambda carry: pending(encode, carry), lambda carry: refresh(encode, carry), (features, changed)
        )
    return features


def apply_with_design_cache(network: nn.Module, variables, cache, *inputs, **kwargs):
    """`network.apply(variables, *inputs, **kwargs)` for one acting step, with the design
    features (their share of the first layer, `ObservationEncoder`) of the worlds whose design
    did not change taken from `cache` (`refresh_design_features`); returns `(outputs, cache)`. Start each rollout from
    `first_design_cache`, since the parameters, and so the features, change between rollouts. A
    network without a design encoder gives `{}`. An empty `cache` (`{}`) is filled: every
    world's design encoded in one pass."""
    outputs, mutated = network.apply({**variables, DESIGN_CACHE: cache}, *inputs, mutable=[DESIGN_CACHE], **kwargs)
    return outputs, mutated.get(DESIGN_CACHE, {})


def first_design_cache(network: nn.Module, variables, *inputs, **kwargs):
    """The cache of a rollout's first step: every world's design in `inputs` encoded in one pass
    (the rest of the network's outputs are unused, so XLA drops them). Why not an empty cache for
    the first step: its loop would encode the whole batch a chunk at a time, a pass per chunk,
    which costs a rollout of few steps (a replay learner's 8) more than the cache saves."""
    return apply_with_design_cache(network, variables, {}, *inputs, **kwargs)[1]


def hidden_activation(x: jax.Array, layer_norm: bool) -> jax.Array:
    """A hidden layer's ReLU, after a LayerNorm where the network asks for one (inside a compact
    module: the LayerNorm is a submodule of the caller)."""
    return nn.relu(nn.LayerNorm()(x) if layer_norm else x)


def _one_frame(lead: tuple[int, ...]) -> bool:
    """Whether inputs with leading axes `lead` hold one frame a step, `(T, B)` or `(T, B, 1)`,
    rather than stacks of several frames."""
    return len(lead) == 2 or (len(lead) == 3 and lead[2] == 1)


class ObservationEncoder(nn.Module):
    """Scaled and one-hot window + counters (+ design features, + position) -> an MLP embedding.

    A dynamic task's design features enter only the first layer, and are constant over a run of
    one design, so their product with that layer's rows is computed once per run (per episode
    when acting) and added to the rest of the layer: the same parameters as one dense layer over
    the concatenated inputs, without the design's share of its cost at every step."""

    layout: ObsLayout
    hidden_size: int  # the design encoder's features, and the MLP's widths unless `layers`
    layers: tuple[int, ...] = ()  # the MLP's widths; empty: two layers of `hidden_size`
    layer_norm: bool = False  # LayerNorm before each ReLU (PQN's networks)
    read_design: bool = True  # a dynamic task's design through `DesignEncoder` (off: a network that reads it otherwise)

    @nn.compact
    def __call__(self, obs: jax.Array, layer: Layer = dense) -> jax.Array:
        parts = self.layout.split(obs)
        lead = obs.shape[:-1]
        features = [
            parts["window"].reshape(lead + (-1,)),
            parts["window_classes"].reshape(lead + (-1,)),
            parts["counters"],
        ]
        if "position" in parts:
            features.append(parts["position"])
        if self.layout.num_actions:
            features += [
                parts["previous_window"].reshape(lead + (-1,)),
                parts["previous_window_classes"].reshape(lead + (-1,)),
                parts["last_action"],
            ]
        widths = self.layers or (self.hidden_size,) * 2
        design = parts["design"] if "design" in parts and self.read_design else None
        if design is not None and layer is dense and self._design_once_per_run(design):
            # The first layer of [step features, design features] is step features @ its first
            # rows + design features @ the rest; the second term is constant over a run of one
            # design, so it is computed once per run with the design's features (the same layer
            # and parameters, summed in another order).
            x = jnp.concatenate(features, axis=-1)
            first = layer(widths[0], np.sqrt(2))
            kernel, bias = (self.variables["params"][first.name][k] for k in ("kernel", "bias"))
            x = x @ kernel[: x.shape[-1]] + bias + self.design_features(design, kernel[x.shape[-1] :])
            x, widths = hidden_activation(x, self.layer_norm), widths[1:]
        else:
            if design is not None:
                features.append(self.design_features(design))
            x = jnp.concatenate(features, axis=-1)
        for width in widths:
            x = hidden_activation(layer(width, np.sqrt(2))(x), self.layer_norm)
        return x

    def _design_once_per_run(self, design: jax.Array) -> bool:
        """Whether `design_features` reads `design` once per run (a sequence, or acting with
        the cache; not stacked frames), with the parameters made (not initializing)."""
        return _one_frame(design.shape[:-2]) and not self.is_initializing()

    def design_features(self, design: jax.Array, kernel: jax.Array | None = None) -> jax.Array:
        """`DesignEncoder` features of `design (*lead, *plan)` (times `kernel` where given): once
        per run of one design along
        the time axis where the inputs are a sequence `(T, B, *plan)` (on a CPU in a loop of
        passes, `encode_each_run`; else in one pass bounded by the layout, `encode_design_runs`;
        see `runs_in_a_loop`); for one step `(1, B, *plan)` or one frame `(1, B, 1, *plan)`
        applied with the `DESIGN_CACHE` collection mutable (`apply_with_design_cache`, acting),
        only for the worlds whose design differs from the cached one; at every entry otherwise
        (stacked frames, whose zeroed history changes more often than episodes do)."""
        encoder = DesignEncoder(self.hidden_size)
        encode = encoder if kernel is None else lambda designs: encoder(designs) @ kernel
        width = self.hidden_size if kernel is None else kernel.shape[-1]
        lead = design.shape[:-2]
        one_frame = _one_frame(lead)
        if one_frame and lead[0] == 1 and self.is_mutable_collection(DESIGN_CACHE) and not self.is_initializing():
            current = design.reshape((lead[1],) + design.shape[-2:])
            fresh = not self.has_variable(DESIGN_CACHE, "design")  # `first_design_cache`: one pass
            seen = self.variable(DESIGN_CACHE, "design", jnp.full, current.shape, jnp.nan, current.dtype)
            cached = self.variable(DESIGN_CACHE, "features", jnp.zeros, (lead[1], width), jnp.float32)
            if fresh:
                cached.value = encode(current)
            else:
                cached.value = refresh_design_features(encode, current, seen.value, cached.value)
            seen.value = current
            return cached.value.reshape(lead + (width,))
        if one_frame:
            sequence = design.reshape((lead[0], -1) + design.shape[-2:])  # (T, B, *plan)
            if runs_in_a_loop() and not self.is_initializing() and lead[0] > 1:
                params = {"encoder": self.variables["params"][encoder.name], "kernel": kernel}
                apply = functools.partial(_apply_design_encoder, self.hidden_size)
                features = encode_each_run(apply, params, sequence, run_chunk(sequence.shape[1]))
            else:
                features = encode_design_runs(encode, sequence, self.layout.max_design_runs(lead[0]))
            return features.reshape(lead + features.shape[-1:])
        return encode(design)


class ScannedRNN(nn.Module):
    """A GRU or LSTM over time (`nn.scan`) whose carry is zeroed where `resets` marks a new
    episode. Call with `carry (B, carry_size)` and `(inputs (T, B, F), resets (T, B))`.

    The carry is always one array, so recurrent learners keep it in a runner state and a replay
    sample the same way: the GRU's hidden state, or the LSTM's cell and hidden states side by
    side (`carry_size` = 2 * features).
    """

    features: int
    cell: str = "gru"  # "gru" or "lstm"

    @functools.partial(nn.scan, variable_broadcast="params", in_axes=0, out_axes=0, split_rngs={"params": False})
    @nn.compact
    def __call__(self, carry: jax.Array, step: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        inputs, resets = step
        carry = jnp.where(resets[:, None], jnp.zeros_like(carry), carry)
        inits = dict(kernel_init=scaled_init(1.0), recurrent_kernel_init=scaled_init(1.0))
        if self.cell == "lstm":
            (c, h), out = nn.OptimizedLSTMCell(self.features, **inits)(jnp.split(carry, 2, axis=-1), inputs)
            return jnp.concatenate([c, h], axis=-1), out
        return nn.GRUCell(self.features, **inits)(carry, inputs)


def mlp_head(
    x: jax.Array, hidden_size: int, out: int, gain: float, layer: Layer = dense, layer_norm: bool = False
) -> jax.Array:
    x = hidden_activation(layer(hidden_size, np.sqrt(2))(x), layer_norm)
    return layer(out, gain)(x)


class RecurrentCoreNetwork(nn.Module):
    """Fields and carry of the networks with an optional GRU core (`ActorCritic`,
    `LayerNormQNetwork`): a feed-forward one keeps a `(B, 1)` placeholder carry."""

    layout: ObsLayout
    num_actions: int
    hidden_size: int = 64
    rnn_size: int = 0  # 0: feed-forward

    @property
    def carry_size(self) -> int:
        return self.rnn_size if self.rnn_size else 1

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.carry_size), jnp.float32)


class ActorCritic(RecurrentCoreNetwork):
    """Policy logits and value from the observation, with an optional GRU core."""

    @nn.compact
    def __call__(self, carry: jax.Array, obs: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`carry (B, C)`, `obs (T, B, O)`, `resets (T, B)` -> `(carry, logits (T, B, A), value (T, B))`."""
        x = ObservationEncoder(self.layout, self.hidden_size)(obs)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        logits = mlp_head(x, self.hidden_size, self.num_actions, 0.01)
        value = mlp_head(x, self.hidden_size, 1, 1.0)[..., 0]
        return carry, logits, value


class LayerNormQNetwork(RecurrentCoreNetwork):
    """Q-values `(T, B, A)` with LayerNorm before every hidden ReLU, an optional GRU core, and a
    linear Q layer on top (as in the paper's networks); the call and the carry are `ActorCritic`'s.

    Why LayerNorm: PQN (Gallici et al. 2024) learns without a target network or replay, and the
    normalisation is what keeps its bootstrapped targets from diverging (their analysis of TD
    stability).
    """

    @nn.compact
    def __call__(self, carry: jax.Array, obs: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = ObservationEncoder(self.layout, self.hidden_size, layer_norm=True)(obs)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        return carry, nn.Dense(self.num_actions, kernel_init=scaled_init(1.0))(x)


def param_count(params) -> int:
    return int(sum(np.prod(p.shape) for p in jax.tree.leaves(params)))


class QNetwork(nn.Module):
    """Q-values from a stack of observations, with an optional LSTM core and a dueling head; with
    `atoms` > 1 the logits of each action's return distribution instead (C51), and with `noisy`
    factorised noisy layers (`agents.common.noisy.NoisyDense`) in place of the encoder's and heads' dense ones.

    Time-major like every network of `agents.common.networks`: `carry (B, C)`, `frames (T, B, k, O)` (the
    last k observations, oldest first, zeros before the episode start), `resets (T, B)`.
    """

    layout: ObsLayout
    num_actions: int
    hidden_size: int = 128
    lstm_size: int = 0  # 0: feed-forward
    dueling: bool = True
    atoms: int = 1  # 1: Q-values (T, B, A); more: logits (T, B, A, atoms)
    noisy: bool = False
    sigma0: float = 0.1  # of the noisy layers
    layer_norm: bool = False  # LayerNorm before every hidden ReLU, as in `LayerNormQNetwork`
    # Heads on the core's features for auxiliary losses (`agents.research.drqn_aux`); their outputs are
    # sown into "intermediates", which only a training loss asks for, so acting never computes them.
    auxiliary_heads: nn.Module | None = None

    @property
    def carry_size(self) -> int:
        return 2 * self.lstm_size if self.lstm_size else 1

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.carry_size), jnp.float32)

    @nn.compact
    def __call__(
        self, carry: jax.Array, frames: jax.Array, resets: jax.Array, noise: bool = False, noise_per_world: bool = False
    ):
        """`noise`: the noisy layers draw their noise (rng "noise"), one draw for the batch or, with
        `noise_per_world`, one per (step, world); otherwise they are their mean."""
        layer = noisy_dense(self.sigma0, noise, noise_per_world) if self.noisy else dense
        x = ObservationEncoder(self.layout, self.hidden_size, layer_norm=self.layer_norm)(frames, layer)  # (T, B, k, H)
        if frames.shape[-2] > 1:
            x = hidden_activation(nn.Dense(self.hidden_size)(x.reshape(x.shape[:-2] + (-1,))), self.layer_norm)
        else:
            x = x[..., 0, :]
        if self.lstm_size:
            carry, x = ScannedRNN(self.lstm_size, "lstm")(carry, (x, resets))
        if self.auxiliary_heads is not None:
            self.sow("intermediates", "auxiliary", self.auxiliary_heads(x))
        per_action = (self.num_actions,) if self.atoms == 1 else (self.num_actions, self.atoms)
        advantage = lambda: mlp_head(
            x, self.hidden_size, self.num_actions * self.atoms, 1.0, layer, self.layer_norm
        ).reshape(x.shape[:-1] + per_action)
        if not self.dueling:
            return carry, advantage()
        value = mlp_head(x, self.hidden_size, self.atoms, 1.0, layer, self.layer_norm).reshape(
            x.shape[:-1] + (1,) + per_action[1:]
        )
        advantage = advantage()  # built after the value stream, so parameter names stay those of the plain head
        return carry, value + advantage - advantage.mean(axis=-len(per_action), keepdims=True)


def stack_frames(obs: jax.Array, resets: jax.Array, k: int) -> jax.Array:
    """`(T, B, O)` observations -> `(T - k + 1, B, k, O)` stacks of the last k, oldest first;
    a frame from before the episode of the newest one (a reset in between) is zeros, as when acting."""
    t = obs.shape[0] - k + 1
    frames = []
    for j in range(k):
        frame = obs[j : j + t]
        # Frame j of output i is obs[i + j]; it belongs to the newest frame's episode unless a
        # reset lies in (i + j, i + k - 1].
        later_reset = jnp.zeros_like(resets[:t])
        for m in range(j + 1, k):
            later_reset = later_reset | resets[m : m + t]
        frames.append(jnp.where(later_reset[..., None], 0.0, frame))
    return jnp.stack(frames, axis=2)


def frames_with_history(history: jax.Array | None, obs: jax.Array) -> jax.Array:
    """`(..., k, O)`: the stored earlier frames (if any) followed by `obs (..., O)`."""
    obs = obs[..., None, :].astype(jnp.float32)
    return obs if history is None else jnp.concatenate([history, obs], axis=-2)

"""PQN-RNN that acts on where it believes it is (`pqn-belief`): a belief over its position,
turned into the design it expects around itself, which the Q head reads beside its memory.

Why: the robot sees its window of built cells and, on a dynamic task, the whole design, but not
where it stands (SPEC §6). What it should do next depends on the design *at its position*: drop
while the cell under it is below the design, move on once it is full. A recurrent Q-network
must learn both to localise and to look the design up at a position it holds only implicitly,
and the second is a multiplicative read-out that a small MLP learns slowly. The handcrafted
policy (SPEC §11) does the look-up explicitly from its SLAM estimate, and the authors' follow-up
feeds a DRQN the output of a localisation network trained on the true position. Here the look-up
is explicit: the expected design under the belief, cut to the window's shape and aligned with
it (`expected_design_window`), and that minus the window (what is still missing there, as far
as the belief goes) are inputs of the Q head. With `view_radius` the expected design reaches past
the window, an egocentric map of the design around the robot, which can stand in for the design
encoder's allocentric reading of a dynamic task's design (`design_encoder=False`), at a fraction
of its cost.

Two beliefs, one per run (`belief_filter`):

- **filter** (the default): a histogram filter over rows and over columns, carried beside the
  GRU state. Each step moves the belief along the last action's axis by the cells the move
  covered, whose distribution a small head predicts from the last two windows and the action
  (trained by the move loss on the true count), then keeps the positions whose plan edges agree
  with where the window shows padding (`filter_step`). An episode starts at the plan's corner
  (SPEC §2). It is the handcrafted policy's dead reckoning with the window's shift read by a
  learned head; it ignores what the built cells could add (`agents.research.belief_filter`).
- **learned**: the position head of `agents.research.drqn_aux`, on the GRU state, trained by the
  position loss on the true position; a distribution over rows and one over columns.

The recipe's ingredients, each one switch and one place: the belief (`belief_filter`; the filter's
steps in `agents.research.belief_filter`, its move head `MoveHead`), the design expected under it
(`expected_design_window`, its reach `view_radius`), the design encoder beside it or not
(`design_encoder`), and the two losses that train the belief (`position_coef`, `move_coef`). What
the table's ablations tried and the row did not keep (a map of the bricks laid, read as evidence
of the position or as a compass to the unbuilt design) is on bench/results/beyond.md, with the
commit that trained it.

Honest acting: every belief is computed from the observations alone (the filter's only learned
part reads the windows and the action), and the design it reads is the observation's (a dynamic
task) or the task's one fixed design (a static task, where every episode builds the same design,
part of the task's definition like the step limit). The true position and moves enter only the
losses; the greedy policy's `act` gets the observation, its memory and a key, as every
learner's. The belief reaches the Q head under `stop_gradient`: it is trained by its own loss
alone, so it stays a position estimate rather than whatever the TD error would bend it into.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from agents.common.networks import ObservationEncoder, RecurrentCoreNetwork, ScannedRNN, mlp_head, scaled_init
from agents.learners.pqn import PQNConfig, td_loss
from agents.research.belief_filter import belief_cross_entropy, expected_design_window, filter_step
from agents.research.drqn_aux import AuxiliaryHeads, AuxiliaryOptions, add_rollout_losses, move_directions
from agents.research.pqn_aux import AuxiliaryTransition, PQNAux, require_recurrent
from agents.training.config import option
from snac_jax.config import MAX_STRIDE
from snac_jax.transition import PADDING  # a window cell off the plan (SPEC §2)

# --- the networks ----------------------------------------------------------------------------------------


class MoveHead(nn.Module):
    """Logits of the cells the last move covered, 0..MAX_STRIDE, from the window before and after
    it and the action: what the window's shift shows. The filter's one learned part."""

    hidden_size: int

    @nn.compact
    def __call__(self, parts: dict) -> jax.Array:
        lead = parts["window_classes"].shape[:-2]
        seen = jnp.concatenate(
            [
                parts["window_classes"].reshape(lead + (-1,)),
                parts["previous_window_classes"].reshape(lead + (-1,)),
                parts["last_action"],
            ],
            axis=-1,
        )
        return mlp_head(seen, self.hidden_size, MAX_STRIDE + 1, 1.0)


class BeliefQNetwork(RecurrentCoreNetwork):
    """PQN-RNN's network (LayerNorm encoder, GRU) whose Q head also reads the design expected
    around the believed position and that minus the window, through one hidden LayerNorm layer.

    `auxiliary_heads` (on the GRU state) hold the position head, and the move head where the
    belief is learned; their outputs, and the filter's move head, are sown ("intermediates") for
    the losses, which only the training loss keeps. `moves` (per action its row and column
    direction, drops 0; `move_directions`) given turns the filter on, None reads the belief off
    the position head; the filter's belief rides in the carry after the GRU's state.
    `fixed_design` is a static task's design (nested tuples, plan-shaped), None on a dynamic
    task, whose observation carries the design."""

    auxiliary_heads: nn.Module | None = None
    fixed_design: tuple | None = None
    moves: tuple | None = None
    view_radius: int = 0  # half size of the expected design the Q head reads; 0: the window's
    design_encoder: bool = True  # also read a dynamic task's whole design through `DesignEncoder`

    @property
    def view_shape(self) -> tuple[int, int]:
        (wr, wc), (rows, _) = self.layout.window_shape, self.layout.plan_shape
        if not self.view_radius:
            return wr, wc
        return (1 if rows == 1 else 2 * self.view_radius + 1), 2 * self.view_radius + 1

    @property
    def carry_size(self) -> int:
        rows, cols = self.layout.plan_shape
        return self.rnn_size + (rows + cols if self.moves is not None else 0)

    @nn.compact
    def __call__(self, carry: jax.Array, obs: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array]:
        layout = self.layout
        rows, _ = layout.plan_shape
        x = ObservationEncoder(layout, self.hidden_size, layer_norm=True, read_design=self.design_encoder)(obs)
        gru_carry, x = ScannedRNN(self.rnn_size, "gru")(carry[:, : self.rnn_size], (x, resets))
        heads = {} if self.auxiliary_heads is None else dict(self.auxiliary_heads(x))
        parts = layout.split(obs)
        if self.moves is None:
            position = jax.lax.stop_gradient(heads["position"])
            p_row, p_col = jax.nn.softmax(position[..., :rows]), jax.nn.softmax(position[..., rows:])
            carry = gru_carry
        else:
            heads["move"] = MoveHead(self.hidden_size, name="move_head")(parts)
            belief, (p_row, p_col) = self.run_filter(carry[:, self.rnn_size :], heads["move"], obs, resets)
            carry = jnp.concatenate([gru_carry, belief], axis=-1)
        self.sow("intermediates", "auxiliary", heads)
        self.sow("intermediates", "belief", (p_row, p_col))
        if self.fixed_design is None:
            design = parts["design"]
        else:
            design = jnp.broadcast_to(
                jnp.asarray(self.fixed_design, jnp.float32) / layout.height_scale, obs.shape[:-1] + layout.plan_shape
            )
        expected = expected_design_window(p_row, p_col, design, self.view_shape, PADDING / layout.height_scale)
        (vr, vc), (wr, wc) = self.view_shape, layout.window_shape
        in_window = expected[..., (vr - wr) // 2 : (vr + wr) // 2, (vc - wc) // 2 : (vc + wc) // 2]
        lead = obs.shape[:-1]
        local = jnp.concatenate(
            [expected.reshape(lead + (-1,)), (in_window - parts["window"]).reshape(lead + (-1,))], axis=-1
        )
        h = nn.Dense(self.hidden_size, kernel_init=scaled_init(np.sqrt(2)))(jnp.concatenate([x, local], axis=-1))
        h = nn.relu(nn.LayerNorm()(h))
        return carry, nn.Dense(self.num_actions, kernel_init=scaled_init(1.0))(h)

    def run_filter(self, belief: jax.Array, move_logits: jax.Array, obs: jax.Array, resets: jax.Array):
        """Run `filter_step` along time `(T, B, ...)` from the carried belief `(B, rows + cols)`;
        returns the last belief (for the carry) and the belief after each step, `(T, B, rows)` and
        `(T, B, cols)`. It reads from `obs` the last action's direction and where the window shows
        padding, and from the move head's logits the cells moved, without their gradient: the move
        loss alone trains that head (tests/test_belief.py runs it on real episodes, the move head's
        part given)."""
        rows, _ = self.layout.plan_shape
        p_cells = jax.nn.softmax(jax.lax.stop_gradient(move_logits), axis=-1)
        last_action = self.layout.split(obs)["last_action"]  # one-hot, its last entry "none" at a start
        sign = last_action @ jnp.asarray(np.asarray(self.moves + ((0, 0),), np.float32))
        padding = self.layout.env.window_cells(obs[..., : self.layout.env_obs_size]) == PADDING

        def step(belief, inputs):
            belief = filter_step(belief, *inputs)
            return belief, belief

        (b_row, b_col), beliefs = jax.lax.scan(
            step, (belief[:, :rows], belief[:, rows:]), (resets, p_cells, sign, padding)
        )
        return jnp.concatenate([b_row, b_col], axis=-1), beliefs


# --- the learner ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PQNBeliefConfig(AuxiliaryOptions, PQNConfig):
    """PQN-RNN acting on a position belief (see the module docstring), trained with PQN's tuned
    settings per task (`tuned_as`), its own entries (`agents/tuned/pqn-belief.toml`) and the
    losses its belief learns from. Its settings come from PQN's defaults, the auxiliary losses'
    options (`AuxiliaryOptions`), the fields below, then the two tuned files."""

    algorithm: ClassVar[str] = "pqn-belief"
    paper_method: ClassVar[str] = "pqn"
    tuned_as: ClassVar[str] = "pqn"

    position_coef: float = option(
        5e-3,
        "weight of the loss predicting the true plan position from the GRU state "
        "(trains the learned belief; 0: off, allowed with the filter)",
        low=0,
    )
    move_coef: float = option(
        5e-3,
        "weight of the loss predicting how many cells the last move carried the robot "
        "(trains the filter's move head; 0: off, allowed without the filter)",
        low=0,
    )
    view_radius: int = option(
        0,
        "half size of the expected design around the robot that the Q head reads (0: the "
        "window's; larger: an egocentric view of more of the design)",
        low=0,
    )
    design_encoder: bool = option(
        True, "also read a dynamic task's whole design through the design encoder (off: the egocentric view alone)"
    )
    belief_filter: bool = option(
        True,
        "the belief is a histogram filter driven by a learned move head (trained by "
        "the move loss: move_coef > 0); off: the position head (position_coef > 0)",
    )

    def check(self) -> None:
        super().check()
        require_recurrent(self)
        if self.belief_filter and not self.move_coef:
            raise ValueError(
                "pqn-belief with belief_filter needs move_coef > 0: the move loss trains the filter's move head"
            )
        if self.belief_filter and not self.previous_step:
            raise ValueError(
                "pqn-belief with belief_filter needs previous_step=True: its move head reads the window "
                "before the last action and the action"
            )
        if self.view_radius:
            low, high = view_radius_range(self.env_config())
            if not low <= self.view_radius <= high:
                raise ValueError(
                    f"view_radius must be 0 or in {low}..{high} on {self.task}, got {self.view_radius}: at "
                    f"least the window's half size ({low}), as the view holds the window, and at most "
                    f"{high}, from where the view already shows the whole plan from every position"
                )
        if not self.belief_filter and not self.position_coef:
            raise ValueError(
                "pqn-belief needs position_coef > 0 (or belief_filter): the position loss trains its belief"
            )


def view_radius_range(env_config) -> tuple[int, int]:
    """The view radii that make sense on a task: from the window's half size (the view holds the
    window) to max(rows, cols) - 1, where the view shows the whole plan from every position. A
    wider view adds only padding, at a cost that grows with its size (tracing it alone takes
    minutes for radii in the thousands)."""
    rows, cols = env_config.plan_shape
    return env_config.window_shape[1] // 2, max(rows, cols) - 1


class PQNBelief(PQNAux):
    """`PQNAux` (the auxiliary losses on the GRU state and their recorded targets) with
    `BeliefQNetwork` in place of PQN-RNN's network.

    With `stagger_starts` (PQN's tuned settings) each world's first episode is entered midway but
    marked as a start, so the filter starts it at the corner, wrongly. The floor under every
    position and the padding correction pull it off the corner, but away from the plan's edges
    they only spread it over the cells the window allows; the first episode's `belief_nll` is
    high for that reason. Every later episode starts right.

    The defaults train both heads: with the filter the position loss (5e-3) still trains a
    position head on the GRU state, which nothing reads but which shapes the GRU's features;
    with the learned belief the move loss trains a move head there. So `pqn-belief` with its
    filter is not `pqn-aux` plus a filter alone: its GRU also carries pqn-aux's position loss,
    at ten times pqn-aux's weight."""

    def __init__(self, config: PQNBeliefConfig):
        super().__init__(config)
        base, heads = self.network, self.auxiliary.heads(config.hidden_size)
        moves = None
        if config.belief_filter:  # the move loss trains the filter's own head, not one on the GRU state
            moves = tuple(map(tuple, move_directions(self.env.config).tolist()))
            others = tuple(name for name in heads.heads if name != "move")
            heads = (
                AuxiliaryHeads(plan_shape=heads.plan_shape, hidden_size=heads.hidden_size, heads=others)
                if others
                else None
            )
        self.network = BeliefQNetwork(
            layout=base.layout,
            num_actions=base.num_actions,
            hidden_size=base.hidden_size,
            rnn_size=base.rnn_size,
            auxiliary_heads=heads,
            fixed_design=None if self.layout.dynamic else self._fixed_design(),
            moves=moves,
            view_radius=config.view_radius,
            design_encoder=config.design_encoder,
        )

    def _loss(self, params, carry0, batch: AuxiliaryTransition, targets):
        """PQN-aux's loss, and as a metric (no gradient) how well the belief the Q head read knew
        the true position: its cross-entropy, in the position loss's units."""
        (_, q), sown = self.network.apply(params, carry0, batch.obs, batch.reset, mutable="intermediates")
        loss, info = td_loss(q, batch.action, targets)
        recorded = batch.auxiliary
        loss, info = add_rollout_losses(
            self.auxiliary, loss, info, sown, recorded["position"], recorded.get("built"), batch.action, batch.reset
        )
        p_row, p_col = sown["intermediates"]["belief"][0]
        return loss, {**info, "belief_nll": belief_cross_entropy(p_row, p_col, recorded["position"])}

    def held_belief(self, params, policy_state: dict, obs: jax.Array) -> jax.Array:
        """The belief over plan positions, `(rows, cols)`, that the greedy policy (`policy`) reads
        when it acts on `obs` with `policy_state` (one world, unbatched, as its `act` takes them):
        the product of the row and column marginals the Q head reads. It applies the network to
        the inputs `act` gives it and reads what the network sows; the action stays `act`'s, so a
        caller that also wants the action calls `act` beside it (bench/belief_episodes.py)."""
        net_obs = self.layout.acting_inputs(obs, policy_state)
        _, sown = self.network.apply(
            params,
            policy_state["carry"][None],
            net_obs[None, None],
            policy_state["reset"][None, None],
            mutable="intermediates",
        )
        p_row, p_col = sown["intermediates"]["belief"][0]
        return p_row[0, 0][:, None] * p_col[0, 0][None, :]

    def _fixed_design(self) -> tuple:
        """A static task's design as nested tuples (a hashable module field)."""
        designs = np.asarray(self.env_params.designs)
        if designs.shape[0] != 1:
            raise ValueError(f"a static task has one design; {self.config.task} has {designs.shape[0]}")
        return tuple(map(tuple, designs[0].reshape(self.layout.plan_shape).tolist()))

"""DRQN: the DQN of `agents.learners.dqn` with an LSTM core (paper: 256 units), trained on replayed
sequences whose first `burn_in` steps only warm the recurrent state (its carry is cut from the
gradient), as in R2D2. Everything else (acting, replay, targets, the greedy policy) is the DQN's.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from agents.learners.dqn import DQN, DQNConfig
from agents.training.config import option


@dataclasses.dataclass(frozen=True)
class DRQNConfig(DQNConfig):
    algorithm: ClassVar[str] = "drqn"
    paper_method: ClassVar[str] = "drqn"

    lstm_size: int = option(256, "LSTM units", low=1)
    burn_in: int = option(20, "steps at the start of each sampled sequence that only warm the LSTM state", low=0)
    batch_size: int = option(32, "sampled sequences per gradient step", low=1)
    sequence_length: int = option(40, "steps per sampled sequence that get a loss", low=1)

    @property
    def context(self) -> int:
        return super().context + self.burn_in


class DRQN(DQN):
    def __init__(self, config: DRQNConfig):
        self.lstm_size = config.lstm_size
        self.burn_in = config.burn_in
        super().__init__(config)

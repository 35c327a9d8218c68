"""The Q-head: the last layer of every Q-network, what it outputs and how that reads as Q-values.

Every network (Min et al.'s, Ho's two, Fayjie et al.'s) ends in a hidden layer and takes its head
from a :class:`HeadSpec`: the networks know nothing of which head they carry, so a new head is
written here and nowhere in them.

- ``plain``: one Q-value per action (DQN, Double DQN).
- ``dueling``: a value and an advantage stream (Wang et al. 2016; Min et al.'s Eq. 9),
  Q(s, a) = V(s) + A(s, a) - mean over a' of A(s, a').
- ``quantile``: ``quantiles`` values per action, the return distribution's quantiles at the
  midpoints (2i + 1) / 2K (QR-DQN, Dabney et al. 2018; Min et al.'s public code trains it with
  51); the Q-value is their mean.

A head computes in float32, under mixed precision too: bf16's 8 bits of mantissa would round
Q-values of tens to steps of a quarter, tying actions that differ by less.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

HeadKind = Literal["plain", "dueling", "quantile"]


class QHead(nn.Module):
    """A network's last layer: :meth:`forward` gives the head's output (what the objective
    learns), :meth:`q` the Q-values (B, actions) it means (what acting reads)."""

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        with torch.autocast(device_type=hidden.device.type, enabled=False):
            return self.output(hidden.float())

    def output(self, hidden: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def q(self, output: torch.Tensor) -> torch.Tensor:
        """Q-values (B, actions) of an output of this head."""
        return output


class PlainHead(QHead):
    """One Q-value per action."""

    def __init__(self, features: int, actions: int) -> None:
        super().__init__()
        self.q_layer = nn.Linear(features, actions)

    def output(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.q_layer(hidden)


class DuelingHead(QHead):
    """A value stream (B, 1) and an advantage stream (B, actions), combined by
    :func:`dueling_q`."""

    def __init__(self, features: int, actions: int) -> None:
        super().__init__()
        self.value = nn.Linear(features, 1)
        self.advantage = nn.Linear(features, actions)

    def output(self, hidden: torch.Tensor) -> torch.Tensor:
        return dueling_q(self.value(hidden), self.advantage(hidden))


class QuantileHead(QHead):
    """``quantiles`` values per action (B, actions, quantiles): the return's quantiles at the
    midpoints :meth:`taus`; the Q-value is their mean."""

    def __init__(self, features: int, actions: int, quantiles: int) -> None:
        super().__init__()
        self.actions, self.quantiles = actions, quantiles
        self.theta = nn.Linear(features, actions * quantiles)

    def output(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.theta(hidden).view(-1, self.actions, self.quantiles)

    def q(self, output: torch.Tensor) -> torch.Tensor:
        return output.mean(dim=-1)

    def taus(self, device: torch.device) -> torch.Tensor:
        """(quantiles,) the quantile midpoints (2i + 1) / 2K the outputs estimate."""
        k = self.quantiles
        return (2 * torch.arange(k, device=device, dtype=torch.float32) + 1) / (2 * k)


def dueling_q(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Eq. 9: Q(s, a) = V(s) + A(s, a) - mean over a' of A(s, a'). value (B, 1), advantage
    (B, actions)."""
    return value + advantage - advantage.mean(dim=1, keepdim=True)


@dataclass(frozen=True)
class HeadSpec:
    """Which head a network ends in (a network builds it on its last hidden layer)."""

    kind: HeadKind = "plain"
    quantiles: int = 51
    """the quantile head's quantiles per action (Min et al.'s code: 51)"""

    def __post_init__(self) -> None:
        if self.kind not in ("plain", "dueling", "quantile"):
            raise ValueError(f"head must be plain, dueling or quantile, got {self.kind!r}")
        if self.quantiles < 1:
            raise ValueError(f"quantiles must be >= 1, got {self.quantiles}")

    def build(self, features: int, actions: int) -> QHead:
        """The head on a hidden layer of ``features`` units, for ``actions`` actions."""
        if self.kind == "dueling":
            return DuelingHead(features, actions)
        if self.kind == "quantile":
            return QuantileHead(features, actions, self.quantiles)
        return PlainHead(features, actions)


PLAIN = HeadSpec()

# A head's parameters before heads were a part of their own (the networks held them as ``q``,
# ``value`` and ``advantage``): a checkpoint of then loads with its names moved.
LEGACY_HEAD_NAMES: dict[str, str] = {
    "q.": "head.q_layer.",
    "value.": "head.value.",
    "advantage.": "head.advantage.",
}


def legacy_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A network's state dict with a legacy head's parameter names moved under ``head``."""
    moved = {}
    for name, value in state.items():
        for old, new in LEGACY_HEAD_NAMES.items():
            if name.startswith(old):
                name = new + name[len(old) :]
                break
        moved[name] = value
    return moved

"""What a learner minimises: each objective owns its TD target and its loss.

- :class:`TDObjective` (DQN, Double DQN, Dueling DQN): the target r + gamma * value of s', the
  value the target network's max (DQN) or the target network's value of the online network's
  choice (Double DQN, Min et al.'s Eq. 8); Huber's loss or the squared error of the TD error.
- :class:`QuantileObjective` (QR-DQN, Dabney et al. 2018): the target is a distribution, the
  target network's quantiles of the next state's action (the online network's choice by mean,
  as Min et al.'s QR-DQN code takes it) shifted by r and scaled by gamma; the loss is the
  quantile Huber loss, each estimated quantile against every target one, summed over the
  estimates and averaged over the targets (Dabney et al.'s Eq. 10, the authors' code's
  reduction).

Both take the max or the argmax over the actions ``next_mask`` allows only, and with n-step
returns (:mod:`.replay_memory`) ``reward`` is the window's discounted sum and ``gamma`` each
sample's discount to the state after it. Both return, per sample, the loss (the learner averages it,
weighted by importance under prioritized replay), the TD error's magnitude (prioritized
replay's new priority) and the Q-value of the taken action.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import torch
from torch import nn

from .heads import QHead, QuantileHead


class Terms(NamedTuple):
    """One batch's per-sample loss, TD error magnitude and taken action's Q-value, (B,) each."""

    loss: torch.Tensor
    td_error: torch.Tensor
    q_taken: torch.Tensor


class Transitions(NamedTuple):
    """A batch as tensors: the taken actions (B,) int64, the rewards (B,) float32, whether the
    episodes terminated (B,) bool, the next states' action masks (B, actions) and the
    discounts to them (a float, or (B,) float32 with n-step returns)."""

    action: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    next_mask: torch.Tensor
    gamma: float | torch.Tensor


class Objective(Protocol):
    """What a learner minimises, given the heads' outputs on a batch."""

    head: QHead
    double: bool
    """whether it needs the online network's output on the next states (its choice)"""

    def terms(
        self,
        online: torch.Tensor,
        next_target: torch.Tensor,
        next_online: torch.Tensor | None,
        batch: Transitions,
    ) -> Terms: ...


def masked(q: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``q`` with masked-out actions (mask 0) at -inf; an all-zero mask row masks nothing."""
    allowed = mask.bool() | ~mask.bool().any(dim=1, keepdim=True)
    return q.masked_fill(~allowed, float("-inf"))


def next_action(
    head: QHead, next_target: torch.Tensor, next_online: torch.Tensor | None, mask: torch.Tensor
) -> torch.Tensor:
    """(B, 1) the next state's action the target values: the online network's choice (Double
    DQN) or the target network's own, among the allowed actions."""
    chooser = next_target if next_online is None else next_online
    return masked(head.q(chooser), mask).argmax(dim=1, keepdim=True)


def td_target(
    reward: torch.Tensor,
    terminated: torch.Tensor,
    gamma: float | torch.Tensor,
    next_q_target: torch.Tensor,
    next_mask: torch.Tensor,
    next_q_online: torch.Tensor | None = None,
) -> torch.Tensor:
    """r + gamma * (1 - terminated) * value of s' (Q-values in, a target per sample out). With
    ``next_q_online`` (Double DQN, Eq. 8) the online network picks the action and the target
    network values it; without, the target network's max. Both only over the actions
    ``next_mask`` allows."""
    chooser = next_q_target if next_q_online is None else next_q_online
    choice = masked(chooser, next_mask).argmax(dim=1, keepdim=True)
    next_value = next_q_target.gather(1, choice).squeeze(1)
    return reward + gamma * (1.0 - terminated.float()) * next_value


class TDObjective:
    """The one-value TD error of DQN and its Double and Dueling variants."""

    def __init__(self, head: QHead, double: bool, loss: str, huber_delta: float) -> None:
        self.head, self.double = head, double
        self.loss_each: nn.Module = (
            nn.HuberLoss(delta=huber_delta, reduction="none")
            if loss == "huber"
            else nn.MSELoss(reduction="none")
        )

    def terms(
        self,
        online: torch.Tensor,
        next_target: torch.Tensor,
        next_online: torch.Tensor | None,
        batch: Transitions,
    ) -> Terms:
        q_taken = self.head.q(online).gather(1, batch.action[:, None]).squeeze(1)
        with torch.no_grad():
            target = td_target(
                batch.reward,
                batch.terminated,
                batch.gamma,
                self.head.q(next_target),
                batch.next_mask,
                None if next_online is None else self.head.q(next_online),
            )
        loss = self.loss_each(q_taken, target)
        return Terms(loss, (target - q_taken).detach().abs(), q_taken.detach())


class QuantileObjective:
    """QR-DQN's quantile Huber loss between the taken action's quantiles and the target's."""

    def __init__(self, head: QHead, double: bool, kappa: float) -> None:
        if not isinstance(head, QuantileHead):
            raise ValueError("the quantile objective learns a quantile head")
        self.head: QHead = head  # as the Objective protocol types it (an attribute: invariant)
        self.quantile_head = head  # the same head, typed for its taus
        self.double, self.kappa = double, kappa

    def terms(
        self,
        online: torch.Tensor,
        next_target: torch.Tensor,
        next_online: torch.Tensor | None,
        batch: Transitions,
    ) -> Terms:
        quantiles = online.shape[-1]
        index = batch.action[:, None, None].expand(-1, 1, quantiles)
        theta = online.gather(1, index).squeeze(1)  # (B, K)
        with torch.no_grad():
            choice = next_action(self.head, next_target, next_online, batch.next_mask)
            best = next_target.gather(1, choice[:, :, None].expand(-1, 1, quantiles)).squeeze(1)
            gamma = batch.gamma
            discount = gamma[:, None] if isinstance(gamma, torch.Tensor) else gamma
            alive = 1.0 - batch.terminated.float()[:, None]
            target = batch.reward[:, None] + discount * alive * best  # (B, K)
        # u[b, i, j]: target quantile j minus estimated quantile i.
        u = target[:, None, :] - theta[:, :, None]
        small = u.abs() <= self.kappa
        huber = torch.where(small, 0.5 * u**2, self.kappa * (u.abs() - 0.5 * self.kappa))
        tau = self.quantile_head.taus(online.device)[None, :, None]
        weight = (tau - (u.detach() < 0.0).float()).abs()
        loss = (weight * huber / self.kappa).mean(dim=2).sum(dim=1)
        td_error = (target.mean(dim=1) - theta.detach().mean(dim=1)).abs()
        return Terms(loss, td_error, theta.detach().mean(dim=1))

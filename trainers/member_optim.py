"""The optimisers of stacked members (:mod:`.member_network`), each member with its own settings.

``torch.optim`` takes one learning rate per parameter group, while members' parameters are
stacked in one tensor: the optimisers the presets use are elementwise (Adam, PyTorch's RMSProp,
TensorFlow's RMSProp, :mod:`.tf_rmsprop`), so each is written here once with its settings as
(S, 1, ...) tensors, one row a member, and computes what ``torch.optim`` computes for a lone
network (the same formulas, in the same order, up to float rounding). Gradients are clipped by
each member's own norm (``nn.utils.clip_grad_norm_``'s rule, per member).

A member's state is read and written as a lone optimiser's ``state_dict`` (the one
:func:`.learner.build_optimizer` makes for its config), so that a member's checkpoint is a lone
run's: :meth:`MemberOptimizer.member_state_dict`, :meth:`MemberOptimizer.load_member_state_dict`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from .dqn_config import DQNConfig

# Adam's betas (PyTorch's defaults, which DQNConfig does not change).
ADAM_BETAS = (0.9, 0.999)
# The state each optimiser keeps per parameter, in torch.optim's (or TFRMSprop's) names.
STATE_NAMES = {
    "adam": ("exp_avg", "exp_avg_sq"),
    "rmsprop": ("square_avg",),
    "tf-rmsprop": ("ms", "mom"),
}
CENTERED_NAMES = {"rmsprop": "grad_avg", "tf-rmsprop": "mg"}


def shared_setting(configs: Sequence[Any], name: str) -> Any:
    """The value every member's config gives ``name``; raises ValueError naming the members'
    values where they differ (a setting the members' optimiser cannot vary)."""
    values = [getattr(c, name) for c in configs]
    if any(v != values[0] for v in values):
        raise ValueError(f"members must share {name}; they have {values}")
    return values[0]


def _as_laid_out(tensor: torch.Tensor) -> torch.Tensor:
    """A dense tensor viewed in its memory's order (contiguous): a member's dense weights are
    laid out transposed (:class:`.member_network.MemberLinear`), and so are their gradients and
    moments; an elementwise kernel that wants contiguous tensors takes them so."""
    strides = tensor.stride()
    order = sorted(range(tensor.dim()), key=lambda d: strides[d], reverse=True)
    return tensor.permute(order)


class MemberOptimizer:
    """One optimiser step for S members' stacked ``params`` (each (S, ...)), member k with the
    settings of ``configs[k]`` (learning rate, epsilons, RMSProp's decay; the optimiser and
    whether RMSProp is centred must be the same for all)."""

    def __init__(self, params: Sequence[nn.Parameter], configs: Sequence[DQNConfig]) -> None:
        self.params = list(params)
        self.members = len(configs)
        self.kind: str = shared_setting(configs, "optimizer")
        self.centered: bool = self.kind != "adam" and shared_setting(configs, "rmsprop_centered")
        device = self.params[0].device

        def column(values: Sequence[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=device)

        # As floats too: the fused kernel takes them as the lone optimiser does (not float32).
        self.lr_values = [c.learning_rate for c in configs]
        self.eps_values = [c.adam_eps if self.kind == "adam" else c.rmsprop_eps for c in configs]
        self.lr = column(self.lr_values)
        self.eps = column(self.eps_values)
        self.alpha = column([c.rmsprop_alpha for c in configs])
        self.max_norm = [c.grad_clip_norm for c in configs]
        self.steps = torch.zeros(self.members, dtype=torch.float64)
        names = (*STATE_NAMES[self.kind], *([CENTERED_NAMES[self.kind]] if self.centered else []))
        self.state: dict[str, list[torch.Tensor]] = {
            name: [torch.ones_like(p) if name == "ms" else torch.zeros_like(p) for p in self.params]
            for name in names
        }

    def _per_member(self, values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """(S,) values shaped to broadcast over a stacked parameter (S, ...)."""
        return values.reshape(-1, *([1] * (like.dim() - 1)))

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def clip_gradients(self) -> None:
        """Each member's gradients scaled down to its ``grad_clip_norm`` at most (0: not)."""
        if not any(norm > 0.0 for norm in self.max_norm):
            return
        grads = [p.grad for p in self.params if p.grad is not None]
        # As clip_grad_norm_ does for a lone network: each tensor's norm, then their norm.
        each = torch.stack(
            [torch.linalg.vector_norm(g, dim=tuple(range(1, g.dim()))) for g in grads]
        )
        norms = torch.linalg.vector_norm(each, dim=0)
        limit = torch.tensor(
            [n if n > 0.0 else math.inf for n in self.max_norm], device=norms.device
        )
        coef = torch.clamp(limit / (norms + 1e-6), max=1.0)
        for g in grads:
            g.mul_(self._per_member(coef, g))

    @torch.no_grad()
    def step(self) -> None:
        self.steps += 1
        if self.kind == "adam":
            self._adam()
        elif self.kind == "rmsprop":
            self._rmsprop()
        else:
            self._tf_rmsprop()

    def _adam(self) -> None:
        """PyTorch's fused Adam kernel (the lone learner's: :func:`.learner.build_optimizer`),
        once a member on its rows of every parameter: one pass over them, where the
        elementwise formulas took eight and allocated four temporaries (a 5-member
        highway-fast update 7.3 -> 5.2 ms with it)."""
        beta1, beta2 = ADAM_BETAS
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        for k in range(self.members):
            step = torch.tensor(float(self.steps[k]), dtype=torch.float32)
            torch._fused_adam_(
                [_as_laid_out(self.params[i][k]) for i in live],
                [_as_laid_out(self.params[i].grad[k]) for i in live],  # type: ignore[index]
                [_as_laid_out(self.state["exp_avg"][i][k]) for i in live],
                [_as_laid_out(self.state["exp_avg_sq"][i][k]) for i in live],
                [],
                [step] * len(live),
                amsgrad=False,
                lr=self.lr_values[k],
                beta1=beta1,
                beta2=beta2,
                weight_decay=0.0,
                eps=self.eps_values[k],
                maximize=False,
                grad_scale=None,
                found_inf=None,
            )

    def _rmsprop(self) -> None:
        for i, p in enumerate(self.params):
            g = p.grad
            if g is None:
                continue
            alpha = self._per_member(self.alpha, p)
            square = self.state["square_avg"][i]
            square.mul_(alpha).add_((1.0 - alpha) * g * g)
            if self.centered:
                mean = self.state["grad_avg"][i]
                mean.lerp_(g, 1.0 - alpha)
                avg = square.addcmul(mean, mean, value=-1.0).sqrt_()
            else:
                avg = square.sqrt()
            avg = avg.add_(self._per_member(self.eps, p))
            p.sub_(self._per_member(self.lr, p) * g / avg)

    def _tf_rmsprop(self) -> None:
        for i, p in enumerate(self.params):
            g = p.grad
            if g is None:
                continue
            decay = self._per_member(self.alpha, p)
            ms, mom = self.state["ms"][i], self.state["mom"][i]
            ms.add_((g * g - ms) * (1.0 - decay))
            denominator = ms + self._per_member(self.eps, p)
            if self.centered:
                mg = self.state["mg"][i]
                mg.add_((g - mg) * (1.0 - decay))
                denominator = denominator - mg * mg
            mom.copy_(g * self._per_member(self.lr, p) / denominator.sqrt())  # momentum 0
            p.sub_(mom)

    # --- a member's state as a lone optimiser's ---------------------------------------------

    def member_state_dict(self, member: int, lone: torch.optim.Optimizer) -> dict[str, Any]:
        """Member ``member``'s state as ``lone``'s ``state_dict()`` (``lone``: the optimiser
        :func:`.learner.build_optimizer` makes for that member's config, over a lone network's
        parameters in the order of :attr:`params`); ``lone``'s own state is replaced."""
        lone_params = [p for group in lone.param_groups for p in group["params"]]
        if len(lone_params) != len(self.params):
            raise ValueError("the lone optimiser's parameters are not the members' layers")
        lone.state.clear()
        if self.steps[member] > 0:
            for i, p in enumerate(lone_params):
                state: dict[str, Any] = {
                    name: values[i][member].detach().clone() for name, values in self.state.items()
                }
                if self.kind in ("adam", "rmsprop"):
                    state["step"] = torch.tensor(float(self.steps[member]))
                lone.state[p] = state
        return lone.state_dict()

    @torch.no_grad()
    def load_member_state_dict(
        self, member: int, lone: torch.optim.Optimizer, state_dict: dict[str, Any]
    ) -> None:
        """Member ``member``'s state from a lone optimiser's ``state_dict`` (loaded through
        ``lone``, which checks it as torch does)."""
        lone.load_state_dict(state_dict)
        lone_params = [p for group in lone.param_groups for p in group["params"]]
        states = [lone.state.get(p, {}) for p in lone_params]
        if not any(states):  # an optimiser that never stepped
            self.steps[member] = 0
            for name, values in self.state.items():
                for value in values:
                    value[member] = 1.0 if name == "ms" else 0.0
            return
        for name, values in self.state.items():
            for value, state in zip(values, states, strict=True):
                if name not in state:
                    raise ValueError(f"the optimiser's state has no {name!r} for a parameter")
                value[member].copy_(state[name])
        step = states[0].get("step")
        self.steps[member] = float(step) if step is not None else 1.0

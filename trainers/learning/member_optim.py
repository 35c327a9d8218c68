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


def _memory_order(tensor: torch.Tensor) -> list[int]:
    """The member dimension, then the others in their memory's order (largest stride first):
    a member's dense weights are laid out transposed (:class:`.member_network.MemberLinear`)."""
    strides = tensor.stride()
    return [0, *sorted(range(1, tensor.dim()), key=lambda d: strides[d], reverse=True)]


def _views(flat: torch.Tensor, params: Sequence[torch.Tensor]) -> list[torch.Tensor]:
    """Views of the buffer ``flat``, one shaped and laid out as each parameter, one block of
    it after another (each block the parameter's S members, each member's in its memory
    order): every view is dense, so a convolution's weight reshapes without a copy."""
    views, start = [], 0
    for p in params:
        order = _memory_order(p)
        size = p.numel()
        block = flat[start : start + size].view([p.shape[d] for d in order])
        views.append(block.permute([order.index(d) for d in range(p.dim())]))
        start += size
    return views


def _member_rows(views: Sequence[torch.Tensor], member: int) -> list[torch.Tensor]:
    """Member ``member``'s part of each view, viewed in its memory order (contiguous)."""
    return [v[member].permute([d - 1 for d in _memory_order(v)[1:]]) for v in views]


class MemberOptimizer:
    """One optimiser step for S members' stacked ``params`` (each (S, ...)), member k with the
    settings of ``configs[k]`` (learning rate, epsilons, RMSProp's decay; the optimiser and
    whether RMSProp is centred must be the same for all).

    The parameters are moved into one buffer (each becomes a dense view of its block, in the
    layout it had), and so are their gradients and each moment: RMSProp's step is then a few
    operations on whole buffers (each member's settings as a buffer of the same layout),
    clipping a few more, and Adam one fused call a member over lists of views made once, where
    one operation a parameter (or a view built a step) spent more in calls than in arithmetic
    (a 5-member highway-fast update: clipping and Adam 1.03 of 4.45 ms). The gradients stay in
    their buffer (zeroed, not dropped, between updates), so every parameter steps every update,
    as a lone network's do where every parameter has a gradient (all the networks here)."""

    def __init__(self, params: Sequence[nn.Parameter], configs: Sequence[DQNConfig]) -> None:
        self.params = list(params)
        self.members = len(configs)
        self.kind: str = shared_setting(configs, "optimizer")
        self.centered: bool = self.kind != "adam" and shared_setting(configs, "rmsprop_centered")
        first = self.params[0]
        total = sum(p.numel() for p in self.params)

        def buffer(fill: float) -> torch.Tensor:
            return torch.full((total,), fill, dtype=first.dtype, device=first.device)

        with torch.no_grad():
            self.flat = buffer(0.0)
            for p, view in zip(self.params, _views(self.flat, self.params), strict=True):
                view.copy_(p)
                p.data = view
            self.flat_grad = buffer(0.0)
            self.grads = _views(self.flat_grad, self.params)
        for p, grad in zip(self.params, self.grads, strict=True):
            p.grad = grad
        # Each parameter's block of the gradients as (S, its size), for clipping.
        self._grad_blocks, start = [], 0
        for p in self.params:
            self._grad_blocks.append(
                self.flat_grad[start : start + p.numel()].view(self.members, -1)
            )
            start += p.numel()
        # Which member each element of the buffers belongs to.
        member_of = torch.empty(total, dtype=torch.long, device=first.device)
        for view in _views(member_of, self.params):
            view.copy_(torch.arange(self.members).reshape(-1, *[1] * (view.dim() - 1)))

        def per_element(values: Sequence[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=first.dtype, device=first.device)[member_of]

        # As floats too: the fused kernel takes them as the lone optimiser does (not float32).
        self.lr_values = [c.learning_rate for c in configs]
        self.eps_values = [c.adam_eps if self.kind == "adam" else c.rmsprop_eps for c in configs]
        self.lr = per_element(self.lr_values)
        self.eps = per_element(self.eps_values)
        self.alpha = per_element([c.rmsprop_alpha for c in configs])
        self.max_norm = [c.grad_clip_norm for c in configs]
        self.steps = torch.zeros(self.members, dtype=torch.float64)
        names = (*STATE_NAMES[self.kind], *([CENTERED_NAMES[self.kind]] if self.centered else []))
        # Each moment as one buffer, and as views shaped as the parameters.
        self.flat_state = {name: buffer(1.0 if name == "ms" else 0.0) for name in names}
        self.state: dict[str, list[torch.Tensor]] = {
            name: _views(flat, self.params) for name, flat in self.flat_state.items()
        }
        # Adam's kernel's lists, one a member, made once: the views do not change.
        self._adam_rows = [
            (
                _member_rows(self.params, k),
                _member_rows(self.grads, k),
                *(_member_rows(self.state[name], k) for name in STATE_NAMES["adam"]),
            )
            for k in range(self.members)
            if self.kind == "adam"
        ]

    def zero_grad(self) -> None:
        self.flat_grad.zero_()

    def _gathered(self) -> None:
        """Every gradient in the gradient buffer: autograd adds into a gradient that exists,
        in place, so they are there; one it replaced (code that set it to None) is copied in."""
        for p, grad in zip(self.params, self.grads, strict=True):
            if p.grad is not grad:
                with torch.no_grad():
                    grad.copy_(p.grad if p.grad is not None else torch.zeros_like(grad))
                p.grad = grad

    @torch.no_grad()
    def clip_gradients(self) -> None:
        """Each member's gradients scaled down to its ``grad_clip_norm`` at most (0: not)."""
        self._gathered()
        if not any(norm > 0.0 for norm in self.max_norm):
            return
        # clip_grad_norm_'s rule for a lone network (each gradient's norm, then their norm),
        # on each parameter's block as (S, its size).
        norms = torch.linalg.vector_norm(
            torch.stack([torch.linalg.vector_norm(block, dim=1) for block in self._grad_blocks]),
            dim=0,
        )
        limit = torch.tensor(
            [n if n > 0.0 else math.inf for n in self.max_norm], device=norms.device
        )
        coef = torch.clamp(limit / (norms + 1e-6), max=1.0).reshape(-1, 1)
        for block in self._grad_blocks:
            block.mul_(coef)

    @torch.no_grad()
    def step(self) -> None:
        self._gathered()
        self.steps += 1
        if self.kind == "adam":
            self._adam()
        elif self.kind == "rmsprop":
            self._rmsprop()
        else:
            self._tf_rmsprop()

    def _adam(self) -> None:
        """PyTorch's fused Adam kernel (the lone learner's: :func:`.learner.build_optimizer`),
        once a member on its rows of every parameter."""
        beta1, beta2 = ADAM_BETAS
        for k, (params, grads, exp_avgs, exp_avg_sqs) in enumerate(self._adam_rows):
            step = torch.tensor(float(self.steps[k]), dtype=torch.float32)
            torch._fused_adam_(
                params,
                grads,
                exp_avgs,
                exp_avg_sqs,
                [],
                [step] * len(params),
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
        g, p = self.flat_grad, self.flat
        square = self.flat_state["square_avg"]
        square.mul_(self.alpha).add_((1.0 - self.alpha) * g * g)
        if self.centered:
            mean = self.flat_state["grad_avg"]
            mean.lerp_(g, 1.0 - self.alpha)
            avg = square.addcmul(mean, mean, value=-1.0).sqrt_()
        else:
            avg = square.sqrt()
        avg = avg.add_(self.eps)
        p.sub_(self.lr * g / avg)

    def _tf_rmsprop(self) -> None:
        g, p = self.flat_grad, self.flat
        ms, mom = self.flat_state["ms"], self.flat_state["mom"]
        ms.add_((g * g - ms) * (1.0 - self.alpha))
        denominator = ms + self.eps
        if self.centered:
            mg = self.flat_state["mg"]
            mg.add_((g - mg) * (1.0 - self.alpha))
            denominator = denominator - mg * mg
        mom.copy_(g * self.lr / denominator.sqrt())  # momentum 0
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

"""Adam as ``torch.optim.Adam(fused=True)`` computes it, stepped without TorchDynamo.

``torch.optim.Adam.step`` is wrapped (``_use_grad_for_differentiable``) in code that imports
``torch._dynamo`` on every call, 1.5 CPU-seconds on a process's first step, for graph breaks that
only matter under ``torch.compile``, which no training process here uses. :class:`FusedAdam` is
that optimiser (its class, defaults, state, ``state_dict`` and checkpoints are
``torch.optim.Adam``'s) whose step on the CPU calls the same fused kernel directly, in the order
``torch.optim.adam._fused_adam`` does: every parameter's step count up by one, then
``torch._fused_adam_`` over all of them. The numbers are the same bit for bit
(tests/trainers/test_fused_adam.py). Elsewhere (a GPU, a gradient scaler's scale, a closure) it
steps through PyTorch's own path.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch

from .deferred_dynamo import defer_dynamo_import
from .flat_buffers import FlatGroup


class FusedAdam(torch.optim.Adam):
    """``torch.optim.Adam(params, lr=lr, eps=eps, fused=True)``, the other settings
    PyTorch's defaults (betas 0.9 and 0.999, no weight decay, no AMSGrad)."""

    def __init__(
        self, params: Iterable[torch.Tensor], lr: float, eps: float = 1e-8, one_buffer: bool = False
    ) -> None:
        """``one_buffer``: the parameters, their gradients and both moments each in one flat
        buffer (:mod:`.flat_buffers`; the parameters become views of it, in place), so a step
        is one kernel call over one tensor, every parameter's step count one shared tensor,
        and :meth:`gathered_gradients` lets a caller clip every gradient at once. The same numbers
        as a parameter at a time (tests/trainers/test_fused_adam.py)."""
        defer_dynamo_import()
        super().__init__(params, lr=lr, eps=eps, fused=True)
        self._flat = (
            FlatGroup(self.param_groups[0]["params"], {"exp_avg": 0.0, "exp_avg_sq": 0.0})
            if one_buffer and len(self.param_groups) == 1
            else None
        )
        self._step_count = torch.zeros((), dtype=torch.float32)

    def gathered_gradients(self) -> torch.Tensor | None:
        """Every gradient in one buffer, any set from outside copied in (``one_buffer``), else
        None: what a caller clips at once."""
        if self._flat is None:
            return None
        self._flat.gather_gradients()
        return self._flat.grads

    def _direct(self) -> bool:
        """Whether this step can go straight to the kernel: every parameter on the CPU, no
        scale or overflow flag from a gradient scaler, the settings this class makes."""
        if getattr(self, "grad_scale", None) is not None or getattr(self, "found_inf", None):
            return False
        return all(
            not group["amsgrad"]
            and not group["maximize"]
            and not group["decoupled_weight_decay"]
            and not torch.is_tensor(group["lr"])
            and all(p.device.type == "cpu" for p in group["params"])
            for group in self.param_groups
        )

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> Any:
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        if not self._direct():
            if self._flat is not None:
                self._flat.gather_gradients()
            super().step()
            return loss
        if self._flat is not None:
            self._step_flat(self.param_groups[0], self._flat)
            return loss
        for group in self.param_groups:
            params, grads, exp_avgs, exp_avg_sqs, steps = [], [], [], [], []
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:  # as torch.optim.Adam._init_group starts a fused one's state
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                params.append(p)
                grads.append(p.grad)
                exp_avgs.append(state["exp_avg"])
                exp_avg_sqs.append(state["exp_avg_sq"])
                steps.append(state["step"])
            if not params:
                continue
            _adam_kernel(group, params, grads, exp_avgs, exp_avg_sqs, steps)
        return loss

    def _step_flat(self, group: dict[str, Any], flat: FlatGroup) -> None:
        flat.gather_gradients()
        if flat.start_state(self.state):
            # One step count for all, as every parameter's would be (each steps every time).
            self._step_count = torch.zeros((), dtype=torch.float32, device=flat.params.device)
            for p in flat.members:
                self.state[p]["step"] = self._step_count
        _adam_kernel(
            group,
            [flat.params],
            [flat.grads],
            [flat.slots["exp_avg"]],
            [flat.slots["exp_avg_sq"]],
            [self._step_count],
        )

    def zero_grad(self, set_to_none: bool = True) -> None:
        """As ``torch.optim``'s; with ``one_buffer`` the gradients are zeroed in place
        whatever ``set_to_none`` says (they are views of the gradients' buffer)."""
        if self._flat is None:
            super().zero_grad(set_to_none)
        else:
            self._flat.zero_gradients()

    def state_dict(self) -> dict[str, Any]:
        """As ``torch.optim``'s; with ``one_buffer`` each parameter gets a step count of its
        own, as torch's Adam keeps them (one shared tensor, read back by ``torch.load`` as
        one, would be counted once a parameter by torch's Adam)."""
        saved = super().state_dict()
        if self._flat is not None:
            # New dicts: torch's state_dict hands out the live per-parameter dicts themselves.
            saved["state"] = {
                index: {**entry, **({"step": entry["step"].clone()} if "step" in entry else {})}
                for index, entry in saved["state"].items()
            }
        return saved

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """As ``torch.optim``'s; with ``one_buffer`` the moments read go into the buffers and
        the step counts into the one shared count."""
        super().load_state_dict(state_dict)
        flat = self._flat
        if flat is None:
            return
        steps = [self.state[p]["step"] for p in flat.members if "step" in self.state.get(p, {})]
        # The shared count is the direct step's (on the CPU); PyTorch's own step (elsewhere)
        # counts each parameter's, so there each keeps the one it read.
        if flat.take_state(self.state) and flat.params.device.type == "cpu":
            self._step_count = torch.as_tensor(steps[0], dtype=torch.float32).clone()
            for p in flat.members:
                self.state[p]["step"] = self._step_count


def _adam_kernel(
    group: dict[str, Any],
    params: list[torch.Tensor],
    grads: list[torch.Tensor],
    exp_avgs: list[torch.Tensor],
    exp_avg_sqs: list[torch.Tensor],
    steps: list[torch.Tensor],
) -> None:
    """One Adam step as ``torch.optim.adam._fused_adam`` takes it: the step counts up by one,
    then the fused kernel with the group's settings."""
    beta1, beta2 = group["betas"]
    torch._foreach_add_(steps, 1)
    torch._fused_adam_(
        params,
        grads,
        exp_avgs,
        exp_avg_sqs,
        [],
        steps,
        amsgrad=False,
        lr=group["lr"],
        beta1=beta1,
        beta2=beta2,
        weight_decay=group["weight_decay"],
        eps=group["eps"],
        maximize=False,
        grad_scale=None,
        found_inf=None,
    )

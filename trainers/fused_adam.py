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


class FusedAdam(torch.optim.Adam):
    """``torch.optim.Adam(params, lr=lr, eps=eps, fused=True)``, the other settings
    PyTorch's defaults (betas 0.9 and 0.999, no weight decay, no AMSGrad)."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float, eps: float = 1e-8) -> None:
        defer_dynamo_import()
        super().__init__(params, lr=lr, eps=eps, fused=True)

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
    def step(self, closure: Callable[[], float] | None = None) -> Any:  # type: ignore[override]
        if closure is not None or not self._direct():
            return super().step(closure)
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
        return None

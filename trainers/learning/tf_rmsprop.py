"""RMSProp as TensorFlow 1.x's ``tf.train.RMSPropOptimizer`` computes it, for presets whose
authors trained with it (Ho's ``cnn.py``: ``tf.train.RMSPropOptimizer(learning_rate)``, every
other argument TensorFlow's default).

It differs from ``torch.optim.RMSprop`` in three ways that change the updates:

- epsilon is added *inside* the square root: ``lr * g / sqrt(ms + epsilon)`` (PyTorch:
  ``lr * g / (sqrt(ms) + eps)``); TensorFlow's default epsilon is 1e-10;
- the mean square starts at **one** (``_create_slots``: ``init_ops.ones_initializer``), not
  zero, so the first updates are about ``lr * g``, not ``lr * sign(g) / sqrt(1 - decay)``;
- its defaults: decay 0.9, momentum 0, not centred.

The update (TensorFlow's ``ApplyRMSProp`` kernel, ``training_ops.cc``):
``ms <- ms + (g^2 - ms) * (1 - decay)``; ``mom <- momentum * mom + lr * g / sqrt(ms + eps)``;
``var <- var - mom``; centred, ``mg <- mg + (g - mg) * (1 - decay)`` and the root is of
``ms - mg^2 + eps``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch

from .deferred_dynamo import defer_dynamo_import
from .flat_buffers import FlatGroup


def _slots(centered: bool) -> dict[str, float]:
    """TensorFlow's slots and where they start: the mean square at one (``ms``), the
    moment (``mom``) and, centred, the mean gradient (``mg``) at zero."""
    return {"ms": 1.0, "mom": 0.0, **({"mg": 0.0} if centered else {})}


class TFRMSprop(torch.optim.Optimizer):
    """``tf.train.RMSPropOptimizer(lr, decay, momentum, epsilon, centered)``."""

    def __init__(
        self,
        params: Iterable[torch.Tensor] | Iterable[dict[str, Any]],
        lr: float,
        decay: float = 0.9,
        momentum: float = 0.0,
        epsilon: float = 1e-10,
        centered: bool = False,
        one_buffer: bool = False,
    ) -> None:
        """``one_buffer``: move the parameters into one buffer (each becomes a view of it, in
        place: the modules holding them see no change), and their gradients and slots into
        others, so that a step is a dozen operations on whole buffers instead of a dozen a
        parameter: the same numbers, bit for bit; a lone update of Ho's network about 0.5 ms
        faster. Their gradients are then zeroed in place, never dropped (``zero_grad``)."""
        if lr <= 0.0 or not 0.0 <= decay < 1.0 or momentum < 0.0 or epsilon <= 0.0:
            raise ValueError(
                "TensorFlow's RMSProp needs lr > 0, decay in [0, 1), momentum >= 0 and epsilon "
                f"> 0, got lr={lr}, decay={decay}, momentum={momentum}, epsilon={epsilon}"
            )
        defaults = dict(lr=lr, decay=decay, momentum=momentum, epsilon=epsilon, centered=centered)
        defer_dynamo_import()
        super().__init__(params, defaults)
        self._buffers: list[FlatGroup | None] = [
            FlatGroup(group["params"], _slots(centered)) if one_buffer else None
            for group in self.param_groups
        ]

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group, buffers in zip(self.param_groups, self._buffers, strict=True):
            lr, decay, momentum = group["lr"], group["decay"], group["momentum"]
            epsilon, centered = group["epsilon"], group["centered"]
            if buffers is not None:
                # The buffers as one parameter, its gradient and its slots: the same
                # arithmetic below, on a list of one tensor each.
                buffers.gather_gradients()
                buffers.start_state(self.state)
                params, grads = [buffers.params], [buffers.grads]
                ms, mom = [buffers.slots["ms"]], [buffers.slots["mom"]]
                mg = [buffers.slots["mg"]] if centered else []
            else:
                params = [p for p in group["params"] if p.grad is not None]
                if not params:
                    continue
                grads = [p.grad for p in params if p.grad is not None]
                for param in params:
                    state = self.state[param]
                    if not state:
                        state["ms"] = torch.ones_like(param)  # TensorFlow's "rms" slot: ones
                        state["mom"] = torch.zeros_like(param)
                        if centered:
                            state["mg"] = torch.zeros_like(param)
                ms = [self.state[p]["ms"] for p in params]
                mom = [self.state[p]["mom"] for p in params]
                mg = [self.state[p]["mg"] for p in params] if centered else []
            # Every parameter at once (foreach), in the order of TensorFlow's kernel:
            # ms += (g^2 - ms) * (1 - decay); mom = momentum * mom + g * lr / sqrt(ms + eps).
            change = torch._foreach_mul(grads, grads)
            torch._foreach_sub_(change, ms)
            torch._foreach_mul_(change, 1.0 - decay)
            torch._foreach_add_(ms, change)
            denominator = torch._foreach_add(ms, epsilon)
            if centered:
                drift = torch._foreach_sub(grads, mg)
                torch._foreach_mul_(drift, 1.0 - decay)
                torch._foreach_add_(mg, drift)
                torch._foreach_sub_(denominator, torch._foreach_mul(mg, mg))
            torch._foreach_sqrt_(denominator)
            step = torch._foreach_mul(grads, lr)
            torch._foreach_div_(step, denominator)
            torch._foreach_mul_(mom, momentum)
            torch._foreach_add_(mom, step)
            torch._foreach_sub_(params, mom)
        return loss

    def zero_grad(self, set_to_none: bool = True) -> None:
        """As ``torch.optim``'s; with ``one_buffer`` the gradients are zeroed in place
        whatever ``set_to_none`` says (they are views of the gradients' buffer)."""
        if not any(self._buffers):
            super().zero_grad(set_to_none)
            return
        for group, buffers in zip(self.param_groups, self._buffers, strict=True):
            if buffers is not None:
                buffers.zero_gradients()
            else:
                for p in group["params"]:
                    p.grad = None

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """As ``torch.optim``'s; with ``one_buffer`` the slots read go into the buffers."""
        super().load_state_dict(state_dict)
        for buffers in self._buffers:
            if buffers is not None:
                buffers.take_state(self.state)

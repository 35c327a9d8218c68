"""A parameter group's tensors in flat buffers: its parameters, their gradients and each of an
optimiser's per-parameter slots one buffer each, the parameters, gradients and slots the
modules and state dicts see being views of them, shaped as the parameters.

An optimiser's step is then a handful of operations on whole buffers where it was a handful a
parameter: on the small networks here the calls cost more than the arithmetic (Ho's network's
TensorFlow RMSProp step, a dozen foreach operations over ten parameters, was 0.7 ms of a 5 ms
update). Used by :class:`.tf_rmsprop.TFRMSprop` and :class:`.fused_adam.FusedAdam` with
``one_buffer``. The gradients are zeroed in place, never dropped: autograd adds into a gradient
that exists, in place, so they stay the buffer's; one replaced from outside is copied back in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch


class FlatGroup:
    """``params`` moved into one buffer (each parameter becomes a view of its part, in place:
    the modules holding them see no change), with a gradient buffer and one buffer for each of
    ``slots`` (name: the value it starts at)."""

    def __init__(self, params: Sequence[torch.Tensor], slots: Mapping[str, float]) -> None:
        self.members = list(params)
        self.starts = dict(slots)
        total = sum(p.numel() for p in self.members)
        first = self.members[0]

        def buffer(fill: float) -> torch.Tensor:
            return torch.full((total,), fill, dtype=first.dtype, device=first.device)

        self.params, self.grads = buffer(0.0), buffer(0.0)
        self.slots = {name: buffer(fill) for name, fill in self.starts.items()}
        with torch.no_grad():
            for p, view in zip(self.members, self.views(self.params), strict=True):
                view.copy_(p)
                p.data = view
        self.grad_views = self.views(self.grads)
        self.zero_gradients()

    def views(self, flat: torch.Tensor) -> list[torch.Tensor]:
        """``flat`` as one view a parameter, shaped as it."""
        views, start = [], 0
        for p in self.members:
            views.append(flat[start : start + p.numel()].view(p.shape))
            start += p.numel()
        return views

    def zero_gradients(self) -> None:
        self.grads.zero_()
        for p, grad in zip(self.members, self.grad_views, strict=True):
            if p.grad is not grad:
                p.grad = grad

    @torch.no_grad()
    def gather_gradients(self) -> None:
        """Every gradient in the buffer: one set from outside (or dropped) is copied in (as
        zeros)."""
        for p, grad in zip(self.members, self.grad_views, strict=True):
            if p.grad is not grad:
                grad.copy_(p.grad if p.grad is not None else torch.zeros_like(grad))
                p.grad = grad

    def start_state(self, state: dict[Any, dict[str, torch.Tensor]]) -> bool:
        """The state's slots as views of the buffers, from the first step (as the lazy
        per-parameter state starts); returns whether this call started them."""
        if all(state[p] for p in self.members):
            return False
        for name, flat in self.slots.items():
            for p, view in zip(self.members, self.views(flat), strict=True):
                state[p][name] = view
        return True

    @torch.no_grad()
    def take_state(self, state: dict[Any, dict[str, torch.Tensor]]) -> bool:
        """Slots loaded into ``state`` copied into the buffers, the state then their views;
        none loaded (an optimiser that never stepped): the buffers start afresh. Returns
        whether there were slots to take."""
        if not any(state.get(p) for p in self.members):
            for name, flat in self.slots.items():
                flat.fill_(self.starts[name])
            return False
        for name, flat in self.slots.items():
            for p, view in zip(self.members, self.views(flat), strict=True):
                view.copy_(state[p][name])
                state[p][name] = view
        return True

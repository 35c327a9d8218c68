"""Several runs' Q-networks as one network: members stacked along a leading dimension.

S networks of one architecture (S runs of a table that differ in seed, learning rate or any
setting that leaves the shapes alone) are made one module by :func:`stacked_network`, which
takes the S lone networks as :func:`.learner.build_network` builds them (each from its own
seed, so member k starts where a lone run of seed k starts) and replaces their layers:

- every ``nn.Linear`` by a :class:`MemberLinear`: weights (S, out, in), one batched matrix
  product (``baddbmm``) for all members;
- every ``nn.Sequential`` of convolutions by a :class:`MemberConvStack`: the members'
  convolutions as one grouped convolution (``groups=S``), the activations kept as
  (B, S * channels, H, W) in the channels-last layout from the stack's first convolution to its
  ``Flatten`` (grouped convolutions on small images run 2-3x faster so on CPUs), dense
  layers after the flatten as :class:`MemberLinear`;
- every ``nn.LSTM`` (one layer, batch first) by a :class:`MemberLSTM`: the same gates with
  batched matrix products.

The network's own ``forward`` is unchanged: it runs on (S * B, ...) rows, member-major (member
k's batch is rows ``k * B`` to ``(k + 1) * B``), every layer that mixes features being one of
the above. Parameter names are the lone network's, each with a leading member dimension, so
member k's state dict is a lone network's (:func:`member_state`, :func:`load_member_state`),
and a member's checkpoint loads into ``overtake-eval``, ``overtake-export`` and a lone resume.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn


def _stacked(tensors: Sequence[torch.Tensor]) -> nn.Parameter:
    return nn.Parameter(torch.stack([t.detach() for t in tensors]).contiguous())


class MemberLinear(nn.Module):
    """S ``nn.Linear`` layers of one shape on (S * B, in) rows, member-major."""

    def __init__(self, lones: Sequence[nn.Linear]) -> None:
        super().__init__()
        self.members = len(lones)
        self.in_features, self.out_features = lones[0].in_features, lones[0].out_features
        # (S, out, in) as the lone layers' weights, laid out (S, in, out) in memory: the
        # forward's product reads it as it lies, and its gradient comes out of the backward's
        # product in that layout, taken as the gradient without the transposing copy that an
        # (S, out, in) layout costs (the largest copy in a highway-fast member update's profile).
        self.weight = nn.Parameter(
            torch.stack([lone.weight.detach().t() for lone in lones]).transpose(1, 2)
        )
        if any(lone.bias is None for lone in lones):
            raise ValueError("MemberLinear stacks layers with a bias")
        self.bias = _stacked([lone.bias for lone in lones if lone.bias is not None])  # (S, out)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        members = self.members
        x = rows.reshape(members, -1, self.in_features)
        out = torch.baddbmm(self.bias.unsqueeze(1), x, self.weight.transpose(1, 2))
        return out.reshape(-1, self.out_features)


class MemberConv2d(nn.Module):
    """S ``nn.Conv2d`` of one shape as one grouped convolution on (B, S * C, H, W)."""

    def __init__(self, lones: Sequence[nn.Conv2d]) -> None:
        super().__init__()
        first = lones[0]
        if first.groups != 1 or first.padding_mode != "zeros" or first.bias is None:
            raise ValueError("MemberConv2d stacks plain convolutions with a bias")
        self.members = len(lones)
        self.stride, self.padding, self.dilation = first.stride, first.padding, first.dilation
        self.out_channels = first.out_channels
        self.weight = _stacked([lone.weight for lone in lones])  # (S, out, in, kh, kw)
        self.bias = _stacked([lone.bias for lone in lones if lone.bias is not None])  # (S, out)

    def forward(self, grouped: torch.Tensor) -> torch.Tensor:
        weight = self.weight.reshape(-1, *self.weight.shape[2:])
        return F.conv2d(
            grouped,
            weight,
            self.bias.reshape(-1),
            self.stride,
            self.padding,
            self.dilation,
            self.members,
        )


class MemberConvStack(nn.Sequential):
    """A lone network's ``nn.Sequential`` of convolutions (and what follows them up to its
    end: ReLU, max pooling, a flatten, dense layers), for S members at once.

    Input (S * B, C, H, W) rows; the members' channels side by side as (B, S * C, H, W) in
    the channels-last layout through the convolutions; back to (S * B, features) rows at the
    flatten (each member's features in the lone network's (C, H, W) order)."""

    def __init__(self, lones: Sequence[nn.Sequential]) -> None:
        layers: list[nn.Module] = []
        for index, layer in enumerate(lones[0]):
            same = [lone[index] for lone in lones]
            if isinstance(layer, nn.Conv2d):
                layers.append(MemberConv2d(same))  # type: ignore[arg-type]
            elif isinstance(layer, nn.Linear):
                layers.append(MemberLinear(same))  # type: ignore[arg-type]
            elif isinstance(layer, (nn.ReLU, nn.MaxPool2d, nn.Flatten)):
                layers.append(copy.deepcopy(layer))
            else:
                raise ValueError(f"a member convolution stack cannot hold {type(layer).__name__}")
        super().__init__(*layers)
        self.members = len(lones)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        members = self.members
        batch = rows.shape[0] // members
        x = rows.reshape(members, batch, *rows.shape[1:]).transpose(0, 1)
        x = x.reshape(batch, -1, *rows.shape[2:]).contiguous(memory_format=torch.channels_last)
        grouped = True
        for layer in self:
            if isinstance(layer, nn.Flatten):
                # (B, S * C, H, W) -> (S * B, C * H * W), each member's in (C, H, W) order.
                x = x.contiguous().reshape(batch, members, -1).transpose(0, 1)
                x = x.reshape(members * batch, -1)
                grouped = False
            else:
                x = layer(x)
        if grouped:
            channels = x.shape[1] // members
            x = x.contiguous().reshape(batch, members, channels, *x.shape[2:]).transpose(0, 1)
            x = x.reshape(members * batch, channels, *x.shape[3:])
        return x


class MemberLSTM(nn.Module):
    """S one-layer, batch-first ``nn.LSTM`` of one shape on (S * B, T, in) rows; returns
    ``(outputs (S * B, T, hidden), (h, c))`` as the LSTM does (h and c (1, S * B, hidden))."""

    def __init__(self, lones: Sequence[nn.LSTM]) -> None:
        super().__init__()
        first = lones[0]
        if first.num_layers != 1 or not first.batch_first or first.bidirectional:
            raise ValueError("MemberLSTM stacks one-layer, batch-first, one-way LSTMs")
        if first.proj_size:
            raise ValueError("MemberLSTM stacks LSTMs without a projection")
        self.members, self.hidden_size = len(lones), first.hidden_size
        # PyTorch's names, a member dimension first.
        self.weight_ih_l0 = _stacked(
            [_tensor(lone, "weight_ih_l0") for lone in lones]
        )  # (S, 4H, in)
        self.weight_hh_l0 = _stacked(
            [_tensor(lone, "weight_hh_l0") for lone in lones]
        )  # (S, 4H, H)
        self.bias_ih_l0 = _stacked([_tensor(lone, "bias_ih_l0") for lone in lones])  # (S, 4H)
        self.bias_hh_l0 = _stacked([_tensor(lone, "bias_hh_l0") for lone in lones])

    def forward(self, rows: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        members, hidden = self.members, self.hidden_size
        total, steps, features = rows.shape
        batch = total // members
        x = rows.reshape(members, batch * steps, features)
        bias = (self.bias_ih_l0 + self.bias_hh_l0).unsqueeze(1)
        gates_in = torch.baddbmm(bias, x, self.weight_ih_l0.transpose(1, 2))
        gates_in = gates_in.reshape(members, batch, steps, 4 * hidden)
        recurrent = self.weight_hh_l0.transpose(1, 2)
        h = rows.new_zeros(members, batch, hidden)
        c = rows.new_zeros(members, batch, hidden)
        outputs = []
        for t in range(steps):
            gates = torch.baddbmm(gates_in[:, :, t], h, recurrent)
            i, f, g, o = gates.chunk(4, dim=2)  # PyTorch's order: input, forget, cell, output
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
            outputs.append(h)
        out = torch.stack(outputs, dim=2).reshape(total, steps, hidden)
        return out, (h.reshape(1, total, hidden), c.reshape(1, total, hidden))


def _tensor(module: nn.Module, name: str) -> torch.Tensor:
    value = getattr(module, name)
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{type(module).__name__}.{name} is not a tensor")
    return value


MEMBER_LAYERS = (MemberLinear, MemberConv2d, MemberLSTM)


def member_parameter_names(stacked: nn.Module) -> frozenset[str]:
    """The names of ``stacked``'s parameters that hold a member dimension first (all of its
    parameters; its buffers, which members share, hold none)."""
    return frozenset(
        f"{prefix}.{name}" if prefix else name
        for prefix, module in stacked.named_modules()
        if isinstance(module, MEMBER_LAYERS)
        for name in module._parameters
    )


def _replace(stacked: nn.Module, lones: Sequence[nn.Module], prefix: str = "") -> None:
    """Replace, in ``stacked`` (a copy of ``lones[0]``), every layer that holds parameters by
    its member version built from the lones' same layers."""
    for name, child in list(stacked.named_children()):
        same = [lone.get_submodule(prefix + name) for lone in lones]
        member: nn.Module | None = None
        if isinstance(child, nn.Sequential) and any(isinstance(m, nn.Conv2d) for m in child):
            member = MemberConvStack(same)  # type: ignore[arg-type]
        elif isinstance(child, nn.Linear):
            member = MemberLinear(same)  # type: ignore[arg-type]
        elif isinstance(child, nn.LSTM):
            member = MemberLSTM(same)  # type: ignore[arg-type]
        elif isinstance(child, (nn.Conv2d, nn.RNNBase)):
            raise ValueError(
                f"{prefix + name}: a {type(child).__name__} outside a convolution stack"
            )
        if member is not None:
            setattr(stacked, name, member)
        else:
            _replace(child, lones, prefix + name + ".")


def stacked_network(lones: Sequence[nn.Module]) -> nn.Module:
    """One module holding the S networks ``lones`` (one architecture) as members; its forward
    takes (S * B, ...) rows, member-major, and returns (S * B, ...) outputs. Raises ValueError
    where the networks differ in shape or hold a layer it cannot stack."""
    if not lones:
        raise ValueError("stacked_network needs at least one network")
    shapes = [{name: tuple(p.shape) for name, p in lone.state_dict().items()} for lone in lones]
    for index, shape in enumerate(shapes[1:], start=1):
        if shape != shapes[0]:
            differ = sorted(
                k for k in shape.keys() | shapes[0].keys() if shape.get(k) != shapes[0].get(k)
            )
            raise ValueError(
                f"members must share one network shape; member {index} differs from member 0 "
                f"in {', '.join(differ[:4])}"
            )
    stacked = copy.deepcopy(lones[0])
    _replace(stacked, lones)
    if hasattr(stacked, "channels_last"):
        # A lone network's own channels-last copy of its input: its member convolution stacks
        # lay their grouped input out themselves (MemberConvStack).
        # setattr: mypy reads a Module's attributes as tensors or modules.
        setattr(stacked, "channels_last", False)  # noqa: B010
    lone_names = {name for name, _ in lones[0].named_parameters()}
    member_names = {name for name, _ in stacked.named_parameters()}
    if lone_names != member_names:
        raise ValueError(
            "the network holds parameters outside dense, convolution and LSTM layers: "
            + ", ".join(sorted(lone_names ^ member_names))
        )
    if member_parameter_names(stacked) != member_names:
        raise ValueError("a stacked layer holds a parameter without a member dimension")
    return stacked


def member_state(stacked: nn.Module, member: int) -> dict[str, torch.Tensor]:
    """Member ``member``'s state dict, a lone network's (parameters sliced; buffers, which
    members share, as they are); copies, detached from the stacked network."""
    names = member_parameter_names(stacked)
    return {
        name: (value[member] if name in names else value)
        .detach()
        .clone(memory_format=torch.contiguous_format)
        for name, value in stacked.state_dict().items()
    }


@torch.no_grad()
def load_member_state(stacked: nn.Module, member: int, state: dict[str, torch.Tensor]) -> None:
    """Put a lone network's state dict into member ``member`` (raises on other names or
    shapes, as ``load_state_dict`` does)."""
    names = member_parameter_names(stacked)
    own = stacked.state_dict()
    if set(state) != set(own):
        raise ValueError(
            "a member's state must name the network's parameters and buffers; differs in "
            + ", ".join(sorted(set(state) ^ set(own)))
        )
    for name, value in state.items():
        target = own[name][member] if name in names else own[name]
        if tuple(target.shape) != tuple(value.shape):
            raise ValueError(
                f"{name}: the member's is {tuple(target.shape)}, got {tuple(value.shape)}"
            )
        if name in names:
            target.copy_(value)

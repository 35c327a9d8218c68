"""Optimisers without TorchDynamo (trainers/learning/fused_adam.py,
trainers/learning/deferred_dynamo.py).

FusedAdam steps as ``torch.optim.Adam(fused=True)`` does, bit for bit, and their state dicts
are interchangeable; building and stepping the learners' optimisers, and a whole short
training run with no recording, import neither TorchDynamo nor Rerun (what a process's start-up
no longer pays); once TorchDynamo is imported, the optimisers' methods are PyTorch's
dynamo-disabled versions again."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import torch
from torch import nn

from overtake.trainers.learning.fused_adam import FusedAdam


def _network(seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(6, 16), nn.ReLU(), nn.Linear(16, 3))


def _steps(network: nn.Module, optimiser: torch.optim.Optimizer, count: int, seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    for _ in range(count):
        x = torch.randn(32, 6, generator=generator)
        loss = network(x).pow(2).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()


def test_fused_adam_steps_as_torchs_fused_adam_bit_for_bit() -> None:
    for lr, eps in ((1e-3, 1e-8), (5e-4, 0.01)):
        ours_net, torch_net = _network(3), _network(3)
        ours = FusedAdam(ours_net.parameters(), lr=lr, eps=eps)
        theirs = torch.optim.Adam(torch_net.parameters(), lr=lr, eps=eps, fused=True)
        _steps(ours_net, ours, 7, seed=1)
        _steps(torch_net, theirs, 7, seed=1)
        for a, b in zip(ours_net.parameters(), torch_net.parameters(), strict=True):
            assert torch.equal(a, b)
        for a, b in zip(ours.state.values(), theirs.state.values(), strict=True):
            assert a.keys() == b.keys() == {"step", "exp_avg", "exp_avg_sq"}
            assert all(torch.equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a)


def test_fused_adams_state_dict_is_torchs_both_ways() -> None:
    """A checkpoint of either loads into the other, which then goes on as the original."""
    start_net = _network(5)
    first = FusedAdam(start_net.parameters(), lr=1e-3)
    _steps(start_net, first, 3, seed=2)
    saved_net, saved_opt = start_net.state_dict(), first.state_dict()

    ours_net, torch_net = _network(0), _network(0)
    ours_net.load_state_dict(saved_net)
    torch_net.load_state_dict(saved_net)
    ours = FusedAdam(ours_net.parameters(), lr=1e-3)
    theirs = torch.optim.Adam(torch_net.parameters(), lr=1e-3, fused=True)
    # Copies, as a checkpoint read back gives: loading keeps the given tensors themselves.
    ours.load_state_dict(copy.deepcopy(saved_opt))
    theirs.load_state_dict(copy.deepcopy(saved_opt))
    assert theirs.state_dict()["param_groups"] == saved_opt["param_groups"]
    _steps(ours_net, ours, 4, seed=3)
    _steps(torch_net, theirs, 4, seed=3)
    for a, b in zip(ours_net.parameters(), torch_net.parameters(), strict=True):
        assert torch.equal(a, b)
    assert torch.equal(ours.state_dict()["state"][0]["step"], torch.tensor(7.0))


# Run in a fresh interpreter: what a training process imports from its start.
_PROBE = """
import json, sys, torch
from overtake.trainers.learning.dqn_config import DQNConfig
from overtake.trainers.learning.learner import build_optimizer
net = torch.nn.Linear(4, 2)
for kind in ("adam", "tf-rmsprop"):
    opt = build_optimizer(net.parameters(), DQNConfig(optimizer=kind))
    net(torch.ones(3, 4)).sum().backward()
    opt.step()
    opt.zero_grad()
    opt.load_state_dict(opt.state_dict())
before = "torch._dynamo" in sys.modules
import torch._dynamo
opt = build_optimizer(net.parameters(), DQNConfig(optimizer="adam"))
opt.state_dict()
cached = getattr(torch.optim.Optimizer.state_dict.__wrapped__, "__dynamo_disable")
print(json.dumps({"dynamo_before": before, "disabled_after": cached._torchdynamo_disable}))
"""


def test_optimisers_are_built_and_stepped_without_torchdynamo_until_it_is_imported() -> None:
    result = subprocess.run(
        [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120, check=True
    )
    assert json.loads(result.stdout.strip().splitlines()[-1]) == {
        "dynamo_before": False,
        "disabled_after": True,
    }


_RUN = """
import json, runpy, sys
sys.argv = ["overtake-train", "--preset", "ho2018", "--total-steps", "60", "--learning-starts",
            "20", "--batch-size", "8", "--run-dir", sys.argv[1], "--sink", "off", "--no-progress"]
try:
    runpy.run_module("overtake.trainers.train", run_name="__main__")
except SystemExit as exit:
    assert not exit.code, exit.code
print(json.dumps({name: name in sys.modules for name in ("torch._dynamo", "rerun")}))
"""


def test_a_training_run_without_a_recording_imports_neither_torchdynamo_nor_rerun(
    tmp_path: Path,
) -> None:
    result = subprocess.run(
        [sys.executable, "-c", _RUN, str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert json.loads(result.stdout.strip().splitlines()[-1]) == {
        "torch._dynamo": False,
        "rerun": False,
    }


def test_one_buffer_steps_as_a_parameter_at_a_time_and_its_state_dict_is_torchs():
    """The parameters, gradients and moments in flat buffers (build_optimizer's choice): the
    same weights and moments as FusedAdam a parameter at a time after several steps, its
    gradients kept as the buffer's views, and its state dict loads into torch's Adam (and a
    torch Adam's into it), each going on as the other."""
    flat_net, each_net = _network(3), _network(3)
    flat = FusedAdam(flat_net.parameters(), lr=1e-3, eps=1e-4, one_buffer=True)
    each = FusedAdam(each_net.parameters(), lr=1e-3, eps=1e-4)
    _steps(flat_net, flat, 6, seed=4)
    _steps(each_net, each, 6, seed=4)
    for a, b in zip(flat_net.parameters(), each_net.parameters(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(flat.state.values(), each.state.values(), strict=True):
        assert all(torch.equal(a[k], b[k]) for k in ("step", "exp_avg", "exp_avg_sq"))
    # The gradients stayed the buffer's views: autograd added into them, nothing copied in.
    assert all(
        p.grad is g for p, g in zip(flat_net.parameters(), flat._flat.grad_views, strict=True)
    )
    # Both ways through a checkpoint's state dict.
    torch_net = _network(0)
    torch_net.load_state_dict(flat_net.state_dict())
    theirs = torch.optim.Adam(torch_net.parameters(), lr=1e-3, eps=1e-4, fused=True)
    theirs.load_state_dict(copy.deepcopy(flat.state_dict()))
    back_net = _network(0)
    back_net.load_state_dict(each_net.state_dict())
    back = FusedAdam(back_net.parameters(), lr=1e-3, eps=1e-4, one_buffer=True)
    back.load_state_dict(copy.deepcopy(each.state_dict()))
    _steps(torch_net, theirs, 3, seed=5)
    _steps(back_net, back, 3, seed=5)
    _steps(each_net, each, 3, seed=5)
    for a, b, c in zip(
        torch_net.parameters(), back_net.parameters(), each_net.parameters(), strict=True
    ):
        assert torch.equal(a, c) and torch.equal(b, c)
    assert float(back.state_dict()["state"][0]["step"]) == 9.0


def test_one_buffers_state_dict_leaves_its_own_step_count_alone():
    """A state dict taken mid-run (a checkpoint) does not detach the optimiser's own count:
    the next state dict says every step taken since."""
    network = _network(1)
    optimiser = FusedAdam(network.parameters(), lr=1e-3, one_buffer=True)
    _steps(network, optimiser, 2, seed=6)
    assert float(optimiser.state_dict()["state"][0]["step"]) == 2.0
    _steps(network, optimiser, 3, seed=7)
    assert {float(s["step"]) for s in optimiser.state_dict()["state"].values()} == {5.0}


def test_a_closure_is_evaluated_and_the_step_is_the_same():
    """step(closure) returns the closure's loss and steps as a step without one."""
    with_net, without_net = _network(2), _network(2)
    with_opt = FusedAdam(with_net.parameters(), lr=1e-3, one_buffer=True)
    without_opt = FusedAdam(without_net.parameters(), lr=1e-3, one_buffer=True)
    x = torch.randn(16, 6, generator=torch.Generator().manual_seed(8))

    def closure() -> torch.Tensor:
        with_opt.zero_grad()
        loss = with_net(x).pow(2).mean()
        loss.backward()
        return loss

    loss = with_opt.step(closure)
    without_opt.zero_grad()
    without_net(x).pow(2).mean().backward()
    without_opt.step()
    assert loss is not None and float(loss.detach()) > 0.0
    for a, b in zip(with_net.parameters(), without_net.parameters(), strict=True):
        assert torch.equal(a, b)

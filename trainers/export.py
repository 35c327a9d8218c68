"""``overtake-export``: a checkpoint's Q-network as ONNX, checked against PyTorch.

The ONNX model takes the network's inputs as the trainer fed them (the stacked frames of the
sensors it reads, the latest frame of the others; names, shapes and dtypes as the environment
sends them, a free batch axis first) and gives ``q_values`` (batch, 5). What a driver needs to
feed it is in the model's metadata (``overtake``, JSON: format, preset and overrides, inputs,
stack, which inputs are stacked, each observation's space, action names, algorithm and step),
so that :class:`overtake.client.policies.onnx_policy.OnnxPolicy` drives with ONNX Runtime alone.

Before the file is kept, the export is checked: the checkpoint's own preset is driven greedily
by PyTorch for ``--check-decisions`` decisions, and ONNX Runtime's Q-values on every one of
those observations must match PyTorch's (largest difference at most ``--tolerance``) and pick
the same actions. The model is written to a temporary file and renamed into place only then.

Needs the ``export`` extra (onnx, onnxscript, onnxruntime).
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
import tyro
from torch import nn

from overtake.cli import Command, Output, UsageError
from overtake.client.episodes.scenario import Where
from overtake.client.policies.frames import FrameStacker
from overtake.client.policies.onnx_policy import METADATA_KEY, POLICY_FORMAT
from overtake.protocol.vocabulary import (
    ACTION_NAMES,
    HIGHWAY_ENV_ACTION_NAMES,
    HIGHWAY_SCENE_PRESETS,
)

from .learning.network import INPUT_SENSORS, ego_fields_read, observations_read
from .run.checkpoint import Checkpoint, load_checkpoint
from .run.observations import frame_shapes

OUTPUT_NAME = "q_values"


@dataclass(frozen=True)
class ExportConfig:
    """Write a checkpoint's Q-network to ONNX, checked against PyTorch."""

    checkpoint: Annotated[Path, tyro.conf.Positional]
    """the checkpoint (checkpoint.pt of a run directory)"""
    out: Path | None = None
    """the ONNX file; default policy.onnx beside the checkpoint"""
    check_decisions: int = 100
    """decisions of the checkpoint's preset, driven greedily, whose observations check ONNX
    Runtime's Q-values against PyTorch's (0 skips the check)"""
    check_envs: int = 4
    """arenas driven at once for the check"""
    seed: int = 0
    """seed of the check's episodes"""
    tolerance: float = 1e-4
    """largest allowed difference between ONNX Runtime's and PyTorch's Q-values"""
    opset: int = 18
    """the ONNX opset the model is written in"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before the export)."""
        return (Output("--out", self.out),)


class UsedInputs(nn.Module):
    """The Q-network with only the inputs it reads, in its own order (ONNX has no None), and
    its head's output read as Q-values (a quantile head's means)."""

    def __init__(self, network: nn.Module) -> None:
        super().__init__()
        self.network = network
        named: Any = network  # every Q-network class names its inputs
        used = set(named.used_inputs)
        self.names: tuple[str, ...] = tuple(n for n in named.input_names if n in used)
        self.all_names: tuple[str, ...] = tuple(named.input_names)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        given = dict(zip(self.names, inputs, strict=True))
        head: Any = self.network.head  # every Q-network ends in a head
        return head.q(self.network(*(given.get(name) for name in self.all_names)))


def policy_metadata(checkpoint: Checkpoint, names: tuple[str, ...]) -> dict[str, Any]:
    """What a driver needs to feed the exported network, as JSON-ready data."""
    stacked = INPUT_SENSORS[checkpoint.inputs]
    return {
        "format": POLICY_FORMAT,
        "algo": checkpoint.algo,
        "inputs": checkpoint.inputs,
        "preset": checkpoint.preset,
        "overrides": checkpoint.overrides,
        "step": checkpoint.step,
        "stack": checkpoint.dqn.stack,
        # Trained behind the safety shield: drivers put it in front of the model too.
        "shield": bool(checkpoint.config.get("shield", False)),
        "input_names": list(names),
        # The ego vector's fields it reads where not the preset's, which a driver asks the
        # simulator for (OpenRequest.ego_fields); empty: the preset's.
        "ego_fields": list(ego_fields_read(checkpoint.inputs)),
        "stacked": [n for n in names if n in stacked],
        "space": {name: checkpoint.space[name] for name in names},
        # The actions in index order as the preset names them (its behaviour spec's).
        "actions": list(
            HIGHWAY_ENV_ACTION_NAMES if checkpoint.preset in HIGHWAY_SCENE_PRESETS else ACTION_NAMES
        ),
        "output": OUTPUT_NAME,
    }


def example_inputs(checkpoint: Checkpoint, names: tuple[str, ...], batch: int) -> tuple:
    """Zero tensors of the network's inputs for ``batch`` environments."""
    stacked = INPUT_SENSORS[checkpoint.inputs]
    out = []
    for name in names:
        space = checkpoint.space[name]
        shape = tuple(space["shape"])
        if name in stacked:
            shape = (checkpoint.dqn.stack, *shape)
        out.append(torch.zeros((batch, *shape), dtype=getattr(torch, space["dtype"])))
    return tuple(out)


def export_onnx(checkpoint: Checkpoint, path: Path, opset: int) -> UsedInputs:
    """Write the checkpoint's online network to ``path``; returns the exported module."""
    import onnx

    module = UsedInputs(checkpoint.make_learner().online).eval()
    names = module.names
    batch = torch.export.Dim("batch", min=1)
    # The exporter reports optional operator libraries it skips and its own deprecations.
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        warnings.filterwarnings("ignore", message=".*axis name.*will not be used")
        warnings.filterwarnings("ignore", message=".*_flat_weights.*")  # the LSTM's weights
        program = torch.onnx.export(
            module,
            example_inputs(checkpoint, names, 2),
            input_names=list(names),
            output_names=[OUTPUT_NAME],
            dynamic_shapes=(tuple({0: batch} for _ in names),),  # *inputs: one tuple
            opset_version=opset,
            dynamo=True,
            verbose=False,
        )
    assert program is not None
    model = program.model_proto
    entry = model.metadata_props.add()
    entry.key = METADATA_KEY
    entry.value = json.dumps(policy_metadata(checkpoint, names))
    onnx.checker.check_model(model)
    onnx.save_model(model, str(path))
    return module


@dataclass(frozen=True)
class CheckResult:
    decisions: int
    max_abs_diff: float
    same_actions: float
    """the share of decisions where both picked the same (allowed) greedy action"""


def check_against_torch(
    checkpoint: Checkpoint, module: UsedInputs, path: Path, config: ExportConfig
) -> CheckResult:
    """Drive the checkpoint's preset greedily with PyTorch; compare ONNX Runtime's Q-values on
    every observation on the way."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    envs = Where().open(
        checkpoint.preset,
        dict(checkpoint.overrides),
        config.check_envs,
        observations=observations_read(checkpoint.inputs),
        ego_fields=ego_fields_read(checkpoint.inputs),
    )
    try:
        space = envs.single_observation_space
        shapes = frame_shapes(space, checkpoint.inputs, f"preset {checkpoint.preset}")
        stacker = FrameStacker(
            config.check_envs,
            shapes,
            checkpoint.dqn.stack,
            INPUT_SENSORS[checkpoint.inputs],
        )
        obs, info = envs.reset(seed=config.seed)
        stacker.reset(np.arange(config.check_envs), obs)
        worst, same, decisions = 0.0, 0, 0
        resetting = np.zeros(config.check_envs, dtype=bool)
        for _ in range(max(1, config.check_decisions // config.check_envs)):
            stacked = stacker.observation()
            feed = {name: np.ascontiguousarray(stacked[name]) for name in module.names}
            with torch.no_grad():
                want = module(*(torch.from_numpy(feed[n]) for n in module.names)).numpy()
            got = session.run([OUTPUT_NAME], feed)[0]
            worst = max(worst, float(np.abs(got - want).max()))
            allowed = info["action_mask"].astype(bool)
            allowed |= ~allowed.any(axis=1, keepdims=True)
            torch_actions = np.where(allowed, want, -np.inf).argmax(axis=1)
            onnx_actions = np.where(allowed, got, -np.inf).argmax(axis=1)
            same += int((torch_actions == onnx_actions).sum())
            decisions += config.check_envs
            obs, _, terminated, truncated, info = envs.step(torch_actions)
            # Next-step autoreset: the step after an episode ended brings the new episode's
            # first frame, which restarts that arena's stack.
            stacker.take(obs, resetting)
            resetting = terminated | truncated
    finally:
        envs.close()
    return CheckResult(decisions, worst, same / max(decisions, 1))


def main(config: ExportConfig) -> dict[str, Any]:
    """Export and check; returns what was written and measured."""
    if config.check_envs < 1:
        raise UsageError(f"--check-envs must be >= 1, got {config.check_envs}")
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as error:
        raise UsageError(
            f"exporting to ONNX needs onnx, onnxscript and onnxruntime ({error}); "
            'pip install -e ".[export]" installs them'
        ) from None
    checkpoint = load_checkpoint(config.checkpoint)
    out = config.out or config.checkpoint.parent / "policy.onnx"
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o666 & ~umask)  # mkstemp makes it private; the model is as readable as any file
    try:
        module = export_onnx(checkpoint, tmp, config.opset)
        result = None
        if config.check_decisions > 0:
            result = check_against_torch(checkpoint, module, tmp, config)
            if result.max_abs_diff > config.tolerance or result.same_actions < 1.0:
                raise UsageError(
                    f"the ONNX model does not match PyTorch on {result.decisions} decisions of "
                    f"preset {checkpoint.preset}: largest Q-value difference "
                    f"{result.max_abs_diff:.3g} (allowed {config.tolerance:g}), same greedy "
                    f"action in {result.same_actions:.1%}; nothing written to {out}"
                )
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    report = {
        "onnx": str(out),
        "bytes": out.stat().st_size,
        "checkpoint": str(config.checkpoint),
        "preset": checkpoint.preset,
        "inputs": checkpoint.inputs,
        "step": checkpoint.step,
    }
    if result is not None:
        report |= {
            "checked_decisions": result.decisions,
            "max_abs_diff": result.max_abs_diff,
            "same_actions": result.same_actions,
        }
        print(
            f"wrote {out} ({report['bytes']:,} bytes): {checkpoint.algo}/{checkpoint.inputs} "
            f"at step {checkpoint.step}; ONNX Runtime matches PyTorch on {result.decisions} "
            f"decisions of {checkpoint.preset} (largest Q-value difference "
            f"{result.max_abs_diff:.2g}, same actions {result.same_actions:.0%})"
        )
    else:
        print(f"wrote {out} ({report['bytes']:,} bytes), unchecked (--check-decisions 0)")
    return report


COMMAND = Command("overtake-export", ExportConfig, main)


if __name__ == "__main__":
    COMMAND.run()

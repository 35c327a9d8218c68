"""Checkpoints that describe themselves and survive a kill.

A checkpoint is one ``torch.save`` file: a header (format, algorithm, inputs, preset and
overrides, observation spaces, network shape, step, episodes, hyperparameters) and the learner's
state (online and target networks, optimiser), plus the random generators' states for
``--resume``, and what an exact resume needs beyond them (:mod:`.resume`: the replay's account
of its files, the episodes under way, the schedule). It is written to a temporary file in the
same directory, flushed to disk and renamed over the old one, so the old checkpoint stays whole
until the new one is. Loading uses ``weights_only=True``: a checkpoint cannot run code.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

import torch

from overtake.cli import UsageError

from ..learning.grid_network import GridNetworkShape
from ..learning.learner import AnyShape, DQNConfig, DQNLearner, LearnerState, Precision
from ..learning.mlp_network import MlpNetworkShape
from ..learning.network import Inputs, NetworkShape
from ..learning.two_stream_network import TwoStreamShape

CHECKPOINT_FORMAT = "overtake-dqn/1"
CHECKPOINT_NAME = "checkpoint.pt"
REPLAY_DIR_NAME = "replay"
"""the run directory's folder of the replay memory's memory-mapped files"""


class CheckpointError(UsageError):
    """A checkpoint the command was pointed at is missing, unreadable, of another format, or
    of another algorithm, inputs or preset than the run asks for."""


@dataclass(frozen=True)
class Checkpoint:
    algo: str
    inputs: Inputs
    preset: str
    overrides: dict[str, Any]
    space: dict[str, Any]
    net_shape: AnyShape
    dqn: DQNConfig
    step: int
    episodes: int
    resumes: int
    learner: dict[str, Any]
    rng_state: dict[str, Any]
    torch_rng_state: torch.Tensor
    config: dict[str, Any]
    resume: dict[str, Any] | None = None
    """what an exact resume restores (:mod:`.resume`); None in a checkpoint from before it"""

    def check_compatible(self, algo: str, inputs: str, preset: str) -> None:
        if (algo, inputs, preset) != (self.algo, self.inputs, self.preset):
            raise CheckpointError(
                f"--resume: the checkpoint is algo={self.algo} "
                f"inputs={self.inputs} preset={self.preset}, this run asks "
                f"for algo={algo} inputs={inputs} preset={preset}"
            )

    def make_learner(self, device: str = "cpu", precision: Precision = "fp32") -> DQNLearner:
        learner = DQNLearner.for_algo(
            self.algo, self.net_shape, self.inputs, self.dqn, device, precision
        )
        learner.load_state_dict(self.learner)
        return learner


def partial_path(path: Path) -> Path:
    """Where a checkpoint for ``path`` is written before it is renamed over ``path``."""
    return path.with_name(path.name + ".tmp")


def save_checkpoint(
    path: Path,
    *,
    learner: LearnerState,
    config: Any,
    overrides: dict[str, Any],
    space: dict[str, Any],
    net_shape: AnyShape,
    step: int,
    episodes: int,
    rng_state: Mapping[str, Any],
    resumes: int,
    resume: dict[str, Any] | None = None,
) -> None:
    header = {
        "format": CHECKPOINT_FORMAT,
        "algo": config.algo,
        "inputs": config.inputs,
        "preset": config.preset,
        "overrides": overrides,
        "space": space,
        "net_shape": dataclasses.asdict(net_shape),
        "dqn": dataclasses.asdict(config.dqn),
        "step": step,
        "episodes": episodes,
        "resumes": resumes,
        # Plain JSON: loading with weights_only=True accepts no other objects.
        "config_json": json.dumps(plain_data(config)),
    }
    payload = {
        "header": header,
        "learner": learner.state_dict(),
        "rng_state": json.dumps(rng_state),
        "torch_rng_state": torch.get_rng_state(),
        **({"resume": resume} if resume is not None else {}),
    }
    tmp = partial_path(path)
    with open(tmp, "wb") as handle:
        torch.save(payload, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def plain_data(value: Any) -> Any:
    """``value`` (a configuration: dataclasses, paths, tuples) as plain JSON-ready data."""
    if isinstance(value, Path):
        return str(value)
    if dataclasses.is_dataclass(value):
        return {f.name: plain_data(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [plain_data(v) for v in value]
    if isinstance(value, dict):
        return {k: plain_data(v) for k, v in value.items()}
    return value


def load_checkpoint(path: Path) -> Checkpoint:
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a truncated or foreign file
        # One line: PyTorch's own text can be a page, and for a pickle of other objects it
        # advises weights_only=False, which would run whatever the file holds.
        text = str(error).strip().splitlines()[0][:120] if str(error).strip() else ""
        detail = "" if not text or "weights_only" in str(error) else f": {text}"
        raise CheckpointError(
            f"{path} is not a checkpoint overtake-train wrote (PyTorch cannot read it as one, "
            f"{type(error).__name__}{detail})"
        ) from None
    header = payload.get("header") if isinstance(payload, dict) else None
    if not isinstance(header, dict) or header.get("format") != CHECKPOINT_FORMAT:
        found = header.get("format") if isinstance(header, dict) else type(payload).__name__
        raise CheckpointError(
            f"{path}: expected an overtake checkpoint of format {CHECKPOINT_FORMAT}, got {found!r}"
        )
    if header.get("inputs") not in get_args(Inputs):
        raise CheckpointError(
            f"{path}: expected inputs one of {list(get_args(Inputs))}, got {header.get('inputs')!r}"
        )
    shape = dict(header["net_shape"])
    net_shape: AnyShape
    if header["inputs"] == "kinematics":
        shape["table_hw"] = tuple(shape["table_hw"])
        shape["hidden"] = tuple(shape["hidden"])
        net_shape = MlpNetworkShape(**shape)
    elif header["inputs"] == "grid":
        shape["grid_hw"] = tuple(shape["grid_hw"])
        net_shape = GridNetworkShape(**shape)
    elif header["inputs"] == "camera-map":
        shape["camera_hwc"] = tuple(shape["camera_hwc"])
        shape["map_hw"] = tuple(shape["map_hw"])
        net_shape = TwoStreamShape(**shape)
    else:
        shape["camera_hw"] = tuple(shape["camera_hw"])
        shape["ego_high"] = tuple(shape["ego_high"])
        net_shape = NetworkShape(**shape)
    return Checkpoint(
        algo=header["algo"],
        inputs=header["inputs"],
        preset=header["preset"],
        overrides=header["overrides"],
        space=header["space"],
        net_shape=net_shape,
        dqn=DQNConfig(**header["dqn"]),
        step=int(header["step"]),
        episodes=int(header["episodes"]),
        resumes=int(header["resumes"]),
        learner=payload["learner"],
        rng_state=json.loads(payload["rng_state"]),
        torch_rng_state=payload["torch_rng_state"],
        config=json.loads(header["config_json"]),
        resume=payload.get("resume"),
    )

"""A trained policy exported to ONNX (``overtake-export``), driven with ONNX Runtime alone.

No PyTorch: the model's metadata says which observations it reads, how many frames it stacks
and the spaces it was trained on; :class:`OnnxPolicy` stacks the frames as the trainer did
(:class:`overtake.client.policies.frames.FrameStacker`) and acts greedily among the allowed actions.
An environment whose observations differ from the model's (another preset, a sensor switched
off, another camera size) is refused with an error naming both.

Needs the ``onnx`` extra (onnxruntime).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from overtake.cli import UsageError
from overtake.client.policies.frames import FrameShapes, FrameStacker, describe_space
from overtake.client.policies.shield import Shield, ShieldedActing
from overtake.protocol.messages import BehaviourSpec

POLICY_FORMAT = "overtake-policy/1"
METADATA_KEY = "overtake"


class OnnxPolicy:
    """Greedy actions of an exported Q-network for ``num_envs`` environments."""

    def __init__(
        self,
        path: Path,
        num_envs: int,
        space: gym.spaces.Dict,
        preset: str,
        threads: int = 1,
        spec: BehaviourSpec | None = None,
        shield: bool | None = None,
    ) -> None:
        """``shield``: put the safety shield in front of the model (None: where the model was
        trained with it, its metadata says); it needs the environment's ``spec``."""
        ort = _onnxruntime()
        self.meta: dict[str, Any] = read_metadata(path)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        trained_on = f"(the model was trained on preset {self.meta['preset']})"
        here = describe_space(space)
        for name in self.meta["input_names"]:
            if name not in here:
                raise UsageError(
                    f"the model reads observation {name!r}, which preset {preset} does not "
                    f"send (it sends {sorted(here)}) {trained_on}"
                )
            if here[name] != self.meta["space"][name]:
                raise UsageError(
                    f"observation {name!r} of preset {preset} is {here[name]}, the model was "
                    f"built for {self.meta['space'][name]} {trained_on}"
                )
        self.names: tuple[str, ...] = tuple(self.meta["input_names"])
        self.output: str = self.meta["output"]
        shapes = FrameShapes(
            {
                name: (tuple(self.meta["space"][name]["shape"]), np.dtype(here[name]["dtype"]))
                for name in self.names
            },
            actions=len(self.meta["actions"]),
        )
        self.stacker = FrameStacker(
            num_envs, shapes, int(self.meta["stack"]), tuple(self.meta["stacked"])
        )
        self.guard: ShieldedActing | None = None
        if self.meta.get("shield", False) if shield is None else shield:
            if spec is None:
                raise UsageError("the safety shield reads the environment's behaviour spec")
            self.guard = ShieldedActing(Shield(spec), num_envs)
            self.episode_extras = self.guard.episode_extras
        # The last decision's Q-values and the shield's overrides (episode records, recordings).
        self.last_q: np.ndarray | None = None
        self.last_overridden: np.ndarray | None = None
        self.latencies_s: list[float] = []
        """wall-clock seconds of each call's inference (stacking included)"""

    def __call__(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], starting: np.ndarray
    ) -> np.ndarray:
        """Actions for every environment; ``starting`` marks those whose episode just began."""
        began = time.perf_counter()
        stacked = self.stacker.take(obs, starting)
        q = self.session.run([self.output], {name: stacked[name] for name in self.names})[0]
        self.last_q = q
        mask = info["action_mask"]
        if self.guard is not None:
            shielded = self.guard.mask(stacked, mask, starting)
            self.guard.count(q, mask, shielded)
            self.last_overridden = self.guard.last_overridden
            mask = shielded
        allowed = np.asarray(mask).astype(bool)
        allowed |= ~allowed.any(axis=1, keepdims=True)
        actions = np.where(allowed, q, -np.inf).argmax(axis=1).astype(np.int64)
        self.latencies_s.append(time.perf_counter() - began)
        return actions


def _onnxruntime() -> Any:
    try:
        import onnxruntime
    except ImportError as error:
        raise UsageError(
            f"driving an ONNX model needs onnxruntime ({error}); "
            'pip install -e ".[onnx]" installs it'
        ) from None
    return onnxruntime


def read_metadata(path: Path) -> dict[str, Any]:
    """The ``overtake`` metadata of a model ``overtake-export`` wrote (what it reads, the preset
    it was trained on, ...); a file that is not one is refused saying what it is."""
    ort = _onnxruntime()
    if not path.is_file():
        raise UsageError(f"no ONNX model at {path}")
    try:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as error:  # ONNX Runtime raises its own classes for a bad file
        raise UsageError(f"{path} is not an ONNX model ONNX Runtime can load: {error}") from None
    meta = session.get_modelmeta().custom_metadata_map
    if METADATA_KEY not in meta:
        raise UsageError(
            f"{path} has no {METADATA_KEY!r} metadata: it was not written by overtake-export"
        )
    data: dict[str, Any] = json.loads(meta[METADATA_KEY])
    if data.get("format") != POLICY_FORMAT:
        raise UsageError(
            f"{path} is of format {data.get('format')!r}; this version reads {POLICY_FORMAT!r}"
        )
    return data

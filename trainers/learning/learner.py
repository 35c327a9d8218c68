"""One DQN learner made of parts (Min et al. Section III): a network that ends in a Q-head
(:mod:`.heads`), an objective that owns its TD target and loss (:mod:`.objectives`), and a
typed replay batch (:class:`.replay_memory.ReplayBatch`). The algorithms are settings of the parts:

- DQN: a plain head, the target r + gamma * max_a' Q_target(s', a').
- Double DQN (Eq. 8): the online network chooses a' = argmax Q_online(s', a'), the target
  network values it.
- Dueling (Eq. 9): the value and advantage streams, with the Double DQN target.
- QR-DQN (Dabney et al. 2018; Min et al.'s public code trains it too): a quantile head and the
  quantile Huber loss, the next action chosen as Double DQN does.

Invalid actions (the action mask, e.g. a lane change with no lane on that side) are never
chosen: not when acting (greedy or random) and not in the target's max or argmax.
The loss is Huber's or the squared error (``loss``; QR-DQN's its quantile Huber loss),
gradients are clipped by norm unless ``grad_clip_norm`` is 0, the optimiser is Adam or RMSProp
(``optimizer``); a target network copied every ``target_update_steps`` environment steps,
epsilon-greedy with a linear schedule. The network is each preset's (:func:`build_network`).
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np
import torch
from torch import nn

from .deferred_dynamo import defer_dynamo_import
from .dqn_config import ALGOS, AlgoSpec, DQNConfig
from .fused_adam import FusedAdam
from .grid_network import GridNetworkKind, GridNetworkShape, GridQNetwork
from .heads import HeadSpec, legacy_state
from .mlp_network import MlpNetworkShape, MlpQNetwork
from .network import Inputs, NetworkShape, QNetwork
from .objectives import Objective, QuantileObjective, TDObjective, Transitions
from .replay_memory import ReplayBatch
from .tf_rmsprop import TFRMSprop
from .two_stream_network import TwoStreamQNetwork, TwoStreamShape

Precision = Literal["fp32", "bf16", "fp16"]
"""fp32: everything in float32. bf16 / fp16: mixed precision, the networks' forward passes
under ``torch.autocast`` in that type while weights, optimiser state, TD targets and the loss
stay float32; fp16 (CUDA only) also scales the loss against gradient underflow."""

_AUTOCAST_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


AnyShape = NetworkShape | GridNetworkShape | TwoStreamShape | MlpNetworkShape


@dataclass(frozen=True)
class NetworkKind:
    """One family of Q-networks, described once: what it reads, the ``DQNConfig.network``
    names it answers to, how its shape is read from an observation space and how it is
    built."""

    reads: str
    """what its inputs are, for messages"""
    networks: tuple[str, ...]
    shape_type: type
    shape_of: Callable[[Any, int, int], Any]
    """(single observation space, actions, stack) -> its shape"""
    build: Callable[[Any, Inputs, DQNConfig, HeadSpec], nn.Module]
    """(shape, inputs, config, head) -> the network"""
    takes_init: bool = False
    """whether it takes Ho's truncated-normal initialisation (DQNConfig.init)"""


def _grid(shape: Any, _inputs: Inputs, config: DQNConfig, head: HeadSpec) -> nn.Module:
    kind: GridNetworkKind = "baseline" if config.network == "baseline" else "proposed"
    init = config.init_std if config.init == "truncated-normal" else None
    return GridQNetwork(shape, kind, head=head, init_std=init)


def _multimodal(shape: Any, inputs: Inputs, config: DQNConfig, head: HeadSpec) -> nn.Module:
    return QNetwork(
        shape, inputs, head=head, lstm_cells=config.lstm_cells, hidden=config.hidden_units
    )


_MIN_ET_AL = NetworkKind(
    "Min et al.'s camera / LIDAR",
    ("multimodal",),
    NetworkShape,
    NetworkShape.from_space,
    _multimodal,
)
NETWORK_KINDS: dict[str, NetworkKind] = {
    "camera": _MIN_ET_AL,
    "lidar": _MIN_ET_AL,
    "both": _MIN_ET_AL,
    "grid": NetworkKind(
        "Ho's occupancy grid",
        ("baseline", "proposed"),
        GridNetworkShape,
        GridNetworkShape.from_space,
        _grid,
        takes_init=True,
    ),
    "camera-map": NetworkKind(
        "Fayjie et al.'s camera and LIDAR map",
        ("two-stream",),
        TwoStreamShape,
        TwoStreamShape.from_space,
        lambda shape, _inputs, _config, head: TwoStreamQNetwork(shape, head=head),
    ),
    "kinematics": NetworkKind(
        "highway-env's Kinematics table",
        ("mlp",),
        MlpNetworkShape,
        MlpNetworkShape.from_space,
        lambda shape, _inputs, _config, head: MlpQNetwork(shape, head=head),
    ),
}
"""Each input configuration's network family (:data:`.network.INPUTS`)."""


def network_shape(space: Any, inputs: Inputs, actions: int, stack: int) -> AnyShape:
    """What the network for ``inputs`` is built for, read from the single observation
    ``space``: Ho's grid network, Fayjie et al.'s two streams, Min et al.'s network or the
    Kinematics MLP (:data:`NETWORK_KINDS`)."""
    return NETWORK_KINDS[inputs].shape_of(space, actions, stack)


def build_network(shape: AnyShape, inputs: Inputs, config: DQNConfig, head: HeadSpec) -> nn.Module:
    """The Q-network ``config.network`` names, for ``inputs`` (:data:`NETWORK_KINDS`): Min et
    al.'s multi-modal network on camera and / or LIDAR, one of Ho's on the occupancy grid,
    Fayjie et al.'s two-stream network on the camera and the LIDAR map, or the MLP on
    highway-env's Kinematics table."""
    kind = NETWORK_KINDS[inputs]
    if config.init != "torch" and not kind.takes_init:
        raise ValueError(f"init {config.init} is Ho's, for his grid networks (inputs grid)")
    if config.network not in kind.networks or not isinstance(shape, kind.shape_type):
        raise ValueError(
            f"inputs {inputs} ({kind.reads}) need network {' or '.join(kind.networks)}, got "
            f"network={config.network!r}"
        )
    return kind.build(shape, inputs, config, head)


def build_optimizer(parameters: Any, config: DQNConfig) -> torch.optim.Optimizer:
    """Adam (Min et al.'s code), PyTorch's RMSProp (Mnih et al.'s settings by default) or
    TensorFlow's (Ho's code, :mod:`.tf_rmsprop`). Adam and TensorFlow's RMSProp are built and
    stepped without importing TorchDynamo (:mod:`.deferred_dynamo`); PyTorch's RMSProp imports
    it on its first step."""
    defer_dynamo_import()
    if config.optimizer == "tf-rmsprop":
        return TFRMSprop(
            parameters,
            lr=config.learning_rate,
            decay=config.rmsprop_alpha,
            epsilon=config.rmsprop_eps,
            centered=config.rmsprop_centered,
            one_buffer=True,
        )
    if config.optimizer == "rmsprop":
        return torch.optim.RMSprop(
            parameters,
            lr=config.learning_rate,
            alpha=config.rmsprop_alpha,
            eps=config.rmsprop_eps,
            centered=config.rmsprop_centered,
        )
    # The fused kernel (one pass over every parameter, on the CPU too) where torch has it for
    # the device: the single-tensor loop was a third of an update of an MLP (issue 66).
    return FusedAdam(parameters, lr=config.learning_rate, eps=config.adam_eps, one_buffer=True)


@torch.no_grad()
def clip_gradients(optimizer: Any, network: nn.Module, max_norm: float) -> None:
    """``nn.utils.clip_grad_norm_``'s rule (every gradient scaled down so that their norm is
    at most ``max_norm``), on the optimiser's one gradient buffer where it keeps one
    (:class:`.fused_adam.FusedAdam`'s ``one_buffer``): two operations instead of a few a
    parameter; the same up to float rounding."""
    gathered = getattr(optimizer, "gathered_gradients", None)
    flat = gathered() if gathered is not None else None
    if flat is None:
        nn.utils.clip_grad_norm_(network.parameters(), max_norm)
        return
    norm = torch.linalg.vector_norm(flat)
    flat.mul_(torch.clamp(max_norm / (norm + 1e-6), max=1.0))


def execution_device(device: str, precision: Precision = "fp32") -> torch.device:
    """The torch device named ``device``, checked to exist here and to run ``precision``
    (raises ValueError saying what was asked and what this machine has)."""
    try:
        resolved = torch.device(device)
    except RuntimeError as error:
        raise ValueError(f"device {device!r} is not a PyTorch device name: {error}") from None
    if resolved.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(
                f"device {device!r} asked for, but this PyTorch ({torch.__version__}) sees no "
                "CUDA device; use --device cpu, or install a CUDA build of PyTorch on a machine "
                "with a GPU"
            )
        if resolved.index is not None and resolved.index >= count:
            raise ValueError(
                f"device {device!r} asked for, but this machine has {count} CUDA device(s): "
                f"cuda:0..cuda:{count - 1}"
            )
    elif resolved.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device {device!r} asked for, but this PyTorch sees no MPS device")
    elif resolved.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device {device!r}: overtake trains on cpu, cuda or mps")
    if precision not in ("fp32", *_AUTOCAST_DTYPES):
        raise ValueError(f"precision is one of fp32, bf16, fp16, got {precision!r}")
    if precision == "fp16" and resolved.type != "cuda":
        raise ValueError(
            f"precision fp16 needs a CUDA device (its loss scaling is CUDA's), got device "
            f"{device!r}: use bf16 there"
        )
    if precision == "bf16" and resolved.type == "cuda":
        major, minor = torch.cuda.get_device_capability(resolved)
        if major < 8:  # bf16 in hardware from Ampere (compute capability 8.0) on
            raise ValueError(
                f"precision bf16: the GPU of {device!r} (compute capability {major}.{minor}) "
                "runs it only in emulation; use fp16"
            )
    return resolved


def autocast(device: torch.device, precision: Precision) -> contextlib.AbstractContextManager[Any]:
    """Mixed precision for a forward pass on ``device`` (nothing for fp32)."""
    dtype = _AUTOCAST_DTYPES.get(precision)
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


class LearnerState(Protocol):
    """What a training run's books ask of its learner, whether a lone
    :class:`DQNLearner` or a member's place in a :class:`.member_learner.MembersLearner`
    (:class:`.members_run.MemberPlace`): its device and precision, its update count, and its
    state as a lone learner's (what a checkpoint holds)."""

    device: torch.device
    precision: Precision

    @property
    def updates(self) -> int: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> dict[str, bool]: ...


def epsilon_greedy(
    q: np.ndarray, mask: np.ndarray, epsilon: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Epsilon-greedy actions (N,) among the allowed ones (an all-zero mask row allows every
    action) from Q-values (N, actions), and those Q-values; ``rng`` draws the random actions
    and the explore coin, in that order (a lone run's and a member's draws are the same)."""
    allowed = mask.astype(bool)
    allowed |= ~allowed.any(axis=1, keepdims=True)
    greedy = np.where(allowed, q, -np.inf).argmax(axis=1)
    random = np.where(allowed, rng.random(allowed.shape), -1.0).argmax(axis=1)
    explore = rng.random(len(greedy)) < epsilon
    return np.where(explore, random, greedy).astype(np.int64), q


class DQNLearner:
    """The online and target networks, the objective, the optimiser, acting and updating.

    ``algo`` (:data:`ALGOS`): the network's head and whether the target is Double DQN's.
    ``device`` and ``precision`` say where and how the networks run (:data:`Precision`).
    """

    def __init__(
        self,
        shape: AnyShape,
        inputs: Inputs,
        config: DQNConfig,
        algo: AlgoSpec,
        *,
        device: str = "cpu",
        precision: Precision = "fp32",
    ) -> None:
        self.shape, self.inputs, self.config, self.algo = shape, inputs, config, algo
        self.double = algo.double
        self.device = execution_device(device, precision)
        self.precision = precision
        # Loss scaling only for fp16 (bf16 has float32's range); disabled, it passes through.
        self.scaler = torch.amp.GradScaler("cuda", enabled=precision == "fp16")
        head = HeadSpec(algo.head, quantiles=config.quantiles)
        self.online = build_network(shape, inputs, config, head).to(self.device)
        self.target = copy.deepcopy(self.online).eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.optimizer = build_optimizer(self.online.parameters(), config)
        network: Any = self.online  # every network class ends in a head
        self.head = network.head
        self.objective: Objective = (
            QuantileObjective(self.head, algo.double, config.quantile_kappa)
            if algo.head == "quantile"
            else TDObjective(self.head, algo.double, config.loss, config.huber_delta)
        )
        self.updates = 0

    @classmethod
    def for_algo(
        cls,
        algo: str,
        shape: AnyShape,
        inputs: Inputs,
        config: DQNConfig,
        device: str = "cpu",
        precision: Precision = "fp32",
    ) -> DQNLearner:
        """The learner of ``algo`` (one of :data:`ALGOS`)."""
        if algo not in ALGOS:
            raise ValueError(f"unknown algorithm {algo!r}: expected one of {', '.join(ALGOS)}")
        return cls(shape, inputs, config, ALGOS[algo], device=device, precision=precision)

    # --- inputs ---------------------------------------------------------------------------

    def _tensors(self, obs: dict[str, np.ndarray]) -> list[torch.Tensor | None]:
        """The network's inputs in the order it takes them (None for one it leaves out)."""
        network: Any = self.online  # every network class names its inputs
        used = set(network.used_inputs)
        return [
            torch.as_tensor(obs[name], device=self.device) if name in used else None
            for name in network.input_names
        ]

    def _autocast(self) -> contextlib.AbstractContextManager[Any]:
        return autocast(self.device, self.precision)

    # --- acting ---------------------------------------------------------------------------

    @torch.no_grad()
    def q_values(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """(N, actions) float32 Q-values of stacked observations (see
        :class:`.replay_memory.FrameStacker`)."""
        if self.online.training:  # train()/eval() walk every module: only when it changes
            self.online.eval()
        with self._autocast():
            q = self.head.q(self.online(*self._tensors(obs)))
        return q.float().cpu().numpy()

    def act(
        self, obs: dict[str, np.ndarray], mask: np.ndarray, epsilon: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Epsilon-greedy actions (N,) among the allowed ones, and the Q-values (N, actions)."""
        return epsilon_greedy(self.q_values(obs), mask, epsilon, rng)

    # --- learning -------------------------------------------------------------------------

    def update(self, batch: ReplayBatch) -> dict[str, Any]:
        """One gradient step on a replay batch; returns the loss and the mean Q of the taken
        actions, and with prioritized replay (the batch's ``weight``) each sample's TD error's
        magnitude (``td_error``), its new priority."""
        if not self.online.training:
            self.online.train()
        dev = self.device
        gamma: float | torch.Tensor = self.config.gamma
        if np.any(batch.steps != 1):  # n-step returns: gamma ** steps each
            gamma = torch.as_tensor(self.config.gamma**batch.steps, device=dev, dtype=torch.float32)
        transitions = Transitions(
            action=torch.as_tensor(batch.action, device=dev),
            reward=torch.as_tensor(batch.reward, device=dev, dtype=torch.float32),
            terminated=torch.as_tensor(batch.terminated, device=dev),
            next_mask=torch.as_tensor(batch.next_mask, device=dev),
            gamma=gamma,
        )
        # Forward passes in the learner's precision; the heads, targets and loss in float32.
        with self._autocast():
            online = self.online(*self._tensors(batch.obs))
        with torch.no_grad():
            next_inputs = self._tensors(batch.next_obs)
            with self._autocast():
                next_target = self.target(*next_inputs)
                next_online = self.online(*next_inputs) if self.double else None
        terms = self.objective.terms(online, next_target, next_online, transitions)
        if batch.weight is None:
            loss = terms.loss.mean()
        else:  # prioritized replay: each sample's loss times its importance weight
            weight = torch.as_tensor(batch.weight, device=dev, dtype=torch.float32)
            loss = (weight * terms.loss).mean()
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        if self.config.grad_clip_norm > 0.0:
            self.scaler.unscale_(self.optimizer)  # clip the true gradients, not scaled ones
            clip_gradients(self.optimizer, self.online, self.config.grad_clip_norm)
        self.scaler.step(self.optimizer)  # skips the step where fp16 gradients overflowed
        self.scaler.update()
        self.updates += 1
        stats: dict[str, Any] = {
            "loss": float(loss.item()),
            "q_taken": float(terms.q_taken.mean().item()),
        }
        if batch.weight is not None:
            stats["td_error"] = terms.td_error.cpu().numpy()
        return stats

    def sync_target(self) -> None:
        self.target.load_state_dict(self.online.state_dict())

    # --- persistence ----------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            **({"grad_scaler": self.scaler.state_dict()} if self.scaler.is_enabled() else {}),
        }

    def load_state_dict(self, state: dict[str, Any]) -> dict[str, bool]:
        """Restore a :meth:`state_dict`. A checkpoint that carries the online network alone
        (one brought back from another machine without its optimiser's moments) restores
        that: the target network starts as a copy of it and the optimiser afresh. Returns
        which parts were restored (``target``, ``optimizer``), for the run's provenance."""
        self.online.load_state_dict(legacy_state(state["online"]))
        restored = {"target": "target" in state, "optimizer": "optimizer" in state}
        if restored["target"]:
            self.target.load_state_dict(legacy_state(state["target"]))
        else:
            self.target.load_state_dict(self.online.state_dict())
        if restored["optimizer"]:
            self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state.get("updates", 0))
        # An fp16 run resumed from a run in another precision starts with a fresh scale.
        if self.scaler.is_enabled() and "grad_scaler" in state:
            self.scaler.load_state_dict(state["grad_scaler"])
        return restored

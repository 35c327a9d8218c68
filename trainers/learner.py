"""One DQN learner made of parts (Min et al. Section III): a network that ends in a Q-head
(:mod:`.heads`), an objective that owns its TD target and loss (:mod:`.objectives`), and a
typed replay batch (:class:`.replay.ReplayBatch`). The algorithms are settings of the parts:

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
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from .grid_network import GridNetworkKind, GridNetworkShape, GridQNetwork
from .heads import HeadKind, HeadSpec, legacy_state
from .mlp_network import MlpNetworkShape, MlpQNetwork
from .network import Inputs, NetworkShape, QNetwork
from .objectives import Objective, QuantileObjective, TDObjective, Transitions
from .replay import ReplayBatch
from .tf_rmsprop import TFRMSprop
from .two_stream_network import TwoStreamQNetwork, TwoStreamShape

Algo = Literal["dqn", "ddqn", "dueling", "qr"]

Precision = Literal["fp32", "bf16", "fp16"]
"""fp32: everything in float32. bf16 / fp16: mixed precision, the networks' forward passes
under ``torch.autocast`` in that type while weights, optimiser state, TD targets and the loss
stay float32; fp16 (CUDA only) also scales the loss against gradient underflow."""

_AUTOCAST_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


@dataclass(frozen=True)
class AlgoSpec:
    """An algorithm as settings of the learner's parts: the Double DQN target's choice (the
    online network picks the next action) and the network's head."""

    double: bool
    head: HeadKind


# Dueling uses the double target as well, as Wang et al. (2016) did and as Min et al.'s code
# does (Double + Dueling DQN); so does QR-DQN, as their QR-DQN code does.
ALGOS: dict[str, AlgoSpec] = {
    "dqn": AlgoSpec(double=False, head="plain"),
    "ddqn": AlgoSpec(double=True, head="plain"),
    "dueling": AlgoSpec(double=True, head="dueling"),
    "qr": AlgoSpec(double=True, head="quantile"),
}


@dataclass(frozen=True)
class DQNConfig:
    """Hyperparameters. Defaults: Min et al.'s paper and code (Adam 2.5e-4, batch 32, replay
    100,000, 50,000 steps before learning, discount 0.99, epsilon 1 to 0.1 over 1,000,000
    steps, target copy every 10,000 steps)."""

    learning_rate: float = 0.00025
    """the optimiser's step size (Min et al.: 2.5e-4)"""
    batch_size: int = 32
    """transitions per gradient update"""
    replay_size: int = 100_000
    """transitions kept (each frame stored once)"""
    learning_starts: int = 50_000
    """environment steps of experience before the first update"""
    gamma: float = 0.99
    """the discount of future rewards"""
    epsilon_start: float = 1.0
    """the chance of a random action at the start"""
    epsilon_end: float = 0.1
    """the chance of a random action once it has fallen"""
    epsilon_decay_steps: int = 1_000_000
    """environment steps over which epsilon falls linearly from start to end"""
    target_update_steps: int = 10_000
    """environment steps between copies of the online network into the target network"""
    train_every: int = 4
    """environment steps per gradient update (the papers do not say; 4 is Mnih et al.'s)"""
    grad_clip_norm: float = 10.0
    """gradients are scaled down to this norm at most"""
    huber_delta: float = 1.0
    """where the Huber loss turns from squared to linear (loss huber)"""
    stack: int = 4
    """frames (camera), scans (LIDAR) or grids stacked per observation"""
    lstm_cells: int = 256
    """the multimodal network's LSTM cells (Min et al.'s Table II: 256)"""
    hidden_units: int = 512
    """units of the multimodal network's fused layer, before its head"""
    network: Literal["multimodal", "baseline", "proposed", "two-stream", "mlp"] = "multimodal"
    """multimodal: Min et al.'s (camera / LIDAR inputs); baseline or proposed: Ho's networks
    on the occupancy grid (grid inputs; Figs. 4 and 5); two-stream: Fayjie et al.'s (camera-map
    inputs); mlp: a perceptron on highway-env's Kinematics table (kinematics inputs)"""
    optimizer: Literal["adam", "rmsprop", "tf-rmsprop"] = "adam"
    """adam; rmsprop (PyTorch's: epsilon added to the root); tf-rmsprop (TensorFlow 1.x's
    RMSPropOptimizer: epsilon inside the root, the mean square starting at one,
    :mod:`.tf_rmsprop`; Ho's code trains with it)"""
    adam_eps: float = 1e-8
    """Adam's epsilon (PyTorch's default; Min et al.'s notebook: 0.01)"""
    rmsprop_alpha: float = 0.95
    """RMSProp's squared-gradient smoothing (Mnih et al. 2015: 0.95; TensorFlow's decay: 0.9)"""
    rmsprop_eps: float = 0.01
    """RMSProp's epsilon (Mnih et al. 2015's minimum squared gradient: 0.01; TensorFlow's
    default: 1e-10, inside the root)"""
    rmsprop_centered: bool = True
    """RMSProp with a gradient momentum (a mean of the gradient, Mnih et al.'s 0.95 as alpha);
    TensorFlow's default: not centred"""
    loss: Literal["huber", "mse"] = "huber"
    """of the TD error: Huber (Mnih et al. 2015) or squared (Ho's code)"""
    n_step: int = 1
    """rewards summed into each target before bootstrapping (n-step returns, Hessel et al.
    2018 take 3; 1 is the papers' one-step target)"""
    prioritized: bool = False
    """prioritized replay, proportional (Schaul et al. 2016): transitions drawn by their last
    TD error, the loss weighted by importance"""
    priority_alpha: float = 0.6
    """how strongly priorities skew the draw (0: uniform; Schaul et al.'s 0.6)"""
    priority_beta_start: float = 0.4
    """the importance weights' exponent at the start, annealed linearly to 1 over the run's
    budget (Schaul et al.'s 0.4)"""
    priority_eps: float = 1e-6
    """added to each TD error's magnitude, so that no transition is never drawn again"""
    quantiles: int = 51
    """QR-DQN's quantiles per action (Min et al.'s QR-DQN code: 51; Dabney et al.: 200)"""
    quantile_kappa: float = 1.0
    """QR-DQN's quantile Huber loss threshold (Dabney et al. and Min et al.'s code: 1)"""
    store_applied: bool = False
    """store the action the car applied (``info["action_applied"]``: a lane change driver
    assistance refused is keep) instead of the one chosen, so that the learner learns what the
    action did (Krasowski et al. 2023: replacing unsafe actions works best)"""
    intervention_penalty: float = 0.0
    """subtracted from a transition's reward where the safety layer stepped in: the shield
    overrode the network's greedy choice, driver assistance refused the chosen action, or it
    turned a lane change back (Krasowski et al. 2023: a penalty helps learning); 0: none"""

    def __post_init__(self) -> None:
        for name in (
            "batch_size",
            "replay_size",
            "epsilon_decay_steps",
            "target_update_steps",
            "train_every",
            "stack",
            "lstm_cells",
            "hidden_units",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.learning_starts < 0:
            raise ValueError(f"learning_starts must be >= 0, got {self.learning_starts}")
        if not 0.0 < self.learning_rate < 1.0:
            raise ValueError(f"learning_rate must be in (0, 1), got {self.learning_rate}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {self.gamma}")
        for name in ("epsilon_start", "epsilon_end"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.grad_clip_norm < 0.0:
            raise ValueError(f"grad_clip_norm must be >= 0 (0: none), got {self.grad_clip_norm}")
        choices = {
            "network": ("multimodal", "baseline", "proposed", "two-stream", "mlp"),
            "optimizer": ("adam", "rmsprop", "tf-rmsprop"),
            "loss": ("huber", "mse"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if self.n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {self.n_step}")
        if not 0.0 <= self.intervention_penalty <= 100.0:
            raise ValueError(
                f"intervention_penalty must be in [0, 100], got {self.intervention_penalty}"
            )
        if not 0.0 <= self.priority_alpha <= 1.0 or not 0.0 <= self.priority_beta_start <= 1.0:
            raise ValueError(
                "priority_alpha and priority_beta_start must be in [0, 1], got "
                f"{self.priority_alpha} and {self.priority_beta_start}"
            )
        if self.quantiles < 1 or self.quantile_kappa <= 0.0:
            raise ValueError(
                "quantiles must be >= 1 and quantile_kappa > 0, got "
                f"{self.quantiles} and {self.quantile_kappa}"
            )
        if self.priority_eps <= 0.0:
            raise ValueError(f"priority_eps must be > 0, got {self.priority_eps}")
        if self.adam_eps <= 0.0:
            raise ValueError(f"adam_eps must be > 0, got {self.adam_eps}")
        if not 0.0 < self.rmsprop_alpha < 1.0 or self.rmsprop_eps <= 0.0:
            raise ValueError(
                "rmsprop_alpha must be in (0, 1) and rmsprop_eps > 0, got "
                f"{self.rmsprop_alpha} and {self.rmsprop_eps}"
            )

    def priority_beta(self, step: int, total_steps: int) -> float:
        """Prioritized replay's importance exponent after ``step`` of ``total_steps``."""
        fraction = min(max(step, 0) / max(total_steps, 1), 1.0)
        return self.priority_beta_start + fraction * (1.0 - self.priority_beta_start)

    def epsilon(self, step: int) -> float:
        """The exploration rate after ``step`` environment steps."""
        fraction = min(max(step, 0) / self.epsilon_decay_steps, 1.0)
        return self.epsilon_start + fraction * (self.epsilon_end - self.epsilon_start)


AnyShape = NetworkShape | GridNetworkShape | TwoStreamShape | MlpNetworkShape


def network_shape(space: Any, inputs: Inputs, actions: int, stack: int) -> AnyShape:
    """What the network for ``inputs`` is built for, read from the single observation
    ``space``: Ho's grid network, Fayjie et al.'s two streams, or Min et al.'s network."""
    if inputs == "grid":
        return GridNetworkShape.from_space(space, actions, stack)
    if inputs == "camera-map":
        return TwoStreamShape.from_space(space, actions, stack)
    if inputs == "kinematics":
        return MlpNetworkShape.from_space(space, actions, stack)
    return NetworkShape.from_space(space, actions, stack)


def build_network(shape: AnyShape, inputs: Inputs, config: DQNConfig, head: HeadSpec) -> nn.Module:
    """The Q-network ``config.network`` names, for ``inputs``: Min et al.'s multi-modal network
    on camera and / or LIDAR, one of Ho's on the occupancy grid, or Fayjie et al.'s two-stream
    network on the camera and the LIDAR map."""
    if inputs == "kinematics":
        if config.network != "mlp" or not isinstance(shape, MlpNetworkShape):
            raise ValueError(
                "inputs kinematics (highway-env's Kinematics table) need network mlp, got "
                f"network={config.network!r}"
            )
        return MlpQNetwork(shape, head=head)
    if inputs == "camera-map":
        if config.network != "two-stream" or not isinstance(shape, TwoStreamShape):
            raise ValueError(
                "inputs camera-map (Fayjie et al.'s camera and LIDAR map) need network "
                f"two-stream, got network={config.network!r}"
            )
        return TwoStreamQNetwork(shape, head=head)
    if inputs == "grid":
        if config.network not in ("baseline", "proposed") or not isinstance(
            shape, GridNetworkShape
        ):
            raise ValueError(
                "inputs grid (Ho's occupancy grid) need network baseline or proposed, got "
                f"network={config.network!r}"
            )
        kind: GridNetworkKind = "baseline" if config.network == "baseline" else "proposed"
        return GridQNetwork(shape, kind, head=head)
    if config.network != "multimodal" or not isinstance(shape, NetworkShape):
        raise ValueError(
            f"inputs {inputs} (Min et al.'s camera / LIDAR) need network multimodal, got "
            f"network={config.network!r}"
        )
    return QNetwork(
        shape, inputs, head=head, lstm_cells=config.lstm_cells, hidden=config.hidden_units
    )


def build_optimizer(parameters: Any, config: DQNConfig) -> torch.optim.Optimizer:
    """Adam (Min et al.'s code), PyTorch's RMSProp (Mnih et al.'s settings by default) or
    TensorFlow's (Ho's code, :mod:`.tf_rmsprop`)."""
    if config.optimizer == "tf-rmsprop":
        return TFRMSprop(
            parameters,
            lr=config.learning_rate,
            decay=config.rmsprop_alpha,
            epsilon=config.rmsprop_eps,
            centered=config.rmsprop_centered,
        )
    if config.optimizer == "rmsprop":
        return torch.optim.RMSprop(
            parameters,
            lr=config.learning_rate,
            alpha=config.rmsprop_alpha,
            eps=config.rmsprop_eps,
            centered=config.rmsprop_centered,
        )
    return torch.optim.Adam(parameters, lr=config.learning_rate, eps=config.adam_eps)


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
        """Mixed precision for a forward pass (nothing for fp32)."""
        dtype = _AUTOCAST_DTYPES.get(self.precision)
        if dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=dtype)

    # --- acting ---------------------------------------------------------------------------

    @torch.no_grad()
    def q_values(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """(N, actions) float32 Q-values of stacked observations (see
        :class:`.replay.FrameStacker`)."""
        self.online.eval()
        with self._autocast():
            q = self.head.q(self.online(*self._tensors(obs)))
        return q.float().cpu().numpy()

    def act(
        self, obs: dict[str, np.ndarray], mask: np.ndarray, epsilon: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Epsilon-greedy actions (N,) among the allowed ones, and the Q-values (N, actions)."""
        q = self.q_values(obs)
        allowed = mask.astype(bool)
        allowed |= ~allowed.any(axis=1, keepdims=True)
        greedy = np.where(allowed, q, -np.inf).argmax(axis=1)
        random = np.where(allowed, rng.random(allowed.shape), -1.0).argmax(axis=1)
        explore = rng.random(len(greedy)) < epsilon
        return np.where(explore, random, greedy).astype(np.int64), q

    # --- learning -------------------------------------------------------------------------

    def update(self, batch: ReplayBatch) -> dict[str, Any]:
        """One gradient step on a replay batch; returns the loss and the mean Q of the taken
        actions, and with prioritized replay (the batch's ``weight``) each sample's TD error's
        magnitude (``td_error``), its new priority."""
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
            nn.utils.clip_grad_norm_(self.online.parameters(), self.config.grad_clip_norm)
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

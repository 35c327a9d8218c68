"""The learner's settings: which algorithm (:data:`ALGOS`, each a setting of the learner's parts)
and its hyperparameters (:class:`DQNConfig`), each checked where it is made."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from .heads import HeadKind

Algo = Literal["dqn", "ddqn", "dueling", "qr"]


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
    assistance refused is keep; under ho2018's ``ego.applied_as_driven`` what his safety rule
    made of it, as his code stores) instead of the one chosen, so that the learner learns what
    the action did (Krasowski et al. 2023: replacing unsafe actions works best)"""
    bootstrap_time_limit: bool = True
    """bootstrap the target of an episode's last transition where its time limit cut it
    (truncated, not terminated: Gymnasium's reading); False stores it as terminal, no
    bootstrap, as Ho's code does (``gui.py`` passes ``end_episode`` at the frame limit to
    ``remember``, and ``cnn.py`` bootstraps only where it is not set)"""
    init: Literal["torch", "truncated-normal"] = "torch"
    """the weights' start: PyTorch's own (Kaiming-uniform) or, for Ho's grid networks
    (baseline, proposed), every convolution's and dense layer's weights from a normal of
    ``init_std`` cut at two standard deviations and redrawn there, biases zero (Ho's
    ``cnn.py``: ``tf.truncated_normal_initializer(stddev=2e-2)`` as every layer's
    ``kernel_initializer``, TensorFlow's zero biases)"""
    init_std: float = 0.02
    """the truncated normal's standard deviation before its cut (Ho's ``cnn.py``: 0.02)"""
    intervention_penalty: float = 0.0
    """subtracted from a transition's reward where the safety layer stepped in: the shield
    overrode the network's greedy choice, driver assistance refused the chosen action (or,
    under ``ego.applied_as_driven``, Ho's safety rule changed it), or it turned a lane change
    back (Krasowski et al. 2023: a penalty helps learning); 0: none"""

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
            "init": ("torch", "truncated-normal"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if not 0.0 < self.init_std <= 1.0:
            raise ValueError(f"init_std must be in (0, 1], got {self.init_std}")
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

    def stored_terminal(self, terminated: np.ndarray, truncated: np.ndarray) -> np.ndarray:
        """Whether each transition is stored as terminal (no bootstrap): ``terminated``, and
        without ``bootstrap_time_limit`` also ``truncated``."""
        return terminated if self.bootstrap_time_limit else terminated | truncated

    def epsilon(self, step: int) -> float:
        """The exploration rate after ``step`` environment steps."""
        fraction = min(max(step, 0) / self.epsilon_decay_steps, 1.0)
        return self.epsilon_start + fraction * (self.epsilon_end - self.epsilon_start)

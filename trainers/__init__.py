"""DQN, Double DQN, Dueling DQN and QR-DQN trainers for overtake (Min et al. Section III).

They see the simulator only through Gymnasium (the in-process vector env or remote arenas via
overtake.client), never through overtake.server. Commands: ``overtake-train``,
``overtake-eval``, ``overtake-export``, ``overtake-experiment``, ``overtake-replay`` and
``overtake-collision-causes``.
"""

from .learning.learner import ALGOS, DQNConfig, DQNLearner
from .learning.network import NetworkShape, QNetwork
from .learning.replay_memory import FrameStacker, ReplayMemory

__all__ = [
    "ALGOS",
    "DQNConfig",
    "DQNLearner",
    "FrameStacker",
    "NetworkShape",
    "QNetwork",
    "ReplayMemory",
]

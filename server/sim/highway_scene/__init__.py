"""highway-env's highway as a scene of the simulator (``highway_scene.enabled``): its
settings (:mod:`.config`), its compiled decision (:mod:`.kernels`) and its parts
(:mod:`.scene`), which :class:`~overtake.server.sim.core.HighwaySim` takes in place of the
papers' placement, actions and decision."""

from .config import HighwaySceneConfig
from .scene import REWARD_TERMS, MetaActions, SceneDecision, ScenePlacement, check_scene

__all__ = [
    "REWARD_TERMS",
    "HighwaySceneConfig",
    "MetaActions",
    "SceneDecision",
    "ScenePlacement",
    "check_scene",
]

"""ML-Agents' own wrappers over overtake, without the registry download.

mlagents-envs 1.1.0's ``mlagents_envs.envs`` package downloads ML-Agents' example-environment
registry when it is imported (``envs/__init__.py`` reads a manifest from Unity's servers and
needs PyYAML), so ``import mlagents_envs.envs.unity_gym_env`` fails or hangs on a machine that
cannot reach them, and the registry is of no use to overtake anyway. :func:`load_wrappers`
imports the three wrapper modules with a stand-in for that package (the same folder, no
registry), then returns the wrappers::

    from overtake.client import RemoteEnvironment
    from overtake.client.mlagents.wrappers import load_wrappers

    wrappers = load_wrappers()
    env = wrappers.gym(RemoteEnvironment("tcp/127.0.0.1:7447"), allow_multiple_obs=True)

The stand-in stays in ``sys.modules`` for the process (a later ``import mlagents_envs.envs``
finds it, without the registry's environments).

mlagents-envs 1.1.0 declares Python <= 3.10 and numpy < 1.24; it runs on Python 3.11 with
today's numpy when installed without its dependencies (``scripts/setup-mlagents.sh``).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SUPPORTED_MLAGENTS_ENVS = "1.1.0"


class MLAgentsMissing(ImportError):
    """mlagents-envs (or a package its wrappers import) is not installed; the message says
    how to install it."""


@dataclass(frozen=True)
class Wrappers:
    """ML-Agents' wrapper classes: ``gym`` is ``UnityToGymWrapper`` (one agent, gym 0.26's
    API), ``parallel`` is ``UnityParallelEnv`` and ``aec`` ``UnityAECEnv`` (PettingZoo, several
    agents)."""

    gym: Any
    parallel: Any
    aec: Any
    version: str


def load_wrappers() -> Wrappers:
    """Import ML-Agents' wrappers without running ``mlagents_envs.envs.__init__``."""
    try:
        import mlagents_envs
    except ImportError as exc:
        raise MLAgentsMissing(
            f"mlagents-envs {SUPPORTED_MLAGENTS_ENVS} is not installed "
            f"({exc}); scripts/setup-mlagents.sh installs it into .venv"
        ) from exc
    package = "mlagents_envs.envs"
    if package not in sys.modules:
        spec = importlib.util.find_spec("mlagents_envs")
        assert spec is not None and spec.submodule_search_locations is not None
        folder = Path(next(iter(spec.submodule_search_locations))) / "envs"
        stand_in = types.ModuleType(package)
        stand_in.__path__ = [str(folder)]
        stand_in.__package__ = package
        sys.modules[package] = stand_in
    try:
        gym_env = importlib.import_module("mlagents_envs.envs.unity_gym_env")
        parallel_env = importlib.import_module("mlagents_envs.envs.unity_parallel_env")
        aec_env = importlib.import_module("mlagents_envs.envs.unity_aec_env")
    except ImportError as exc:
        raise MLAgentsMissing(
            f"ML-Agents' wrappers need a package that is missing ({exc}): gym 0.26 for "
            "UnityToGymWrapper, pettingzoo for UnityParallelEnv and UnityAECEnv; "
            "scripts/setup-mlagents.sh installs them"
        ) from exc
    version = getattr(mlagents_envs, "__version__", "unknown")
    return Wrappers(
        gym=gym_env.UnityToGymWrapper,
        parallel=parallel_env.UnityParallelEnv,
        aec=aec_env.UnityAECEnv,
        version=version,
    )

"""Golden trajectories: the simulator's behaviour, bit for bit, under fixed seeds and actions.

Every preset at every traffic density is stepped in-process as a single environment and as a
vector environment (next-step autoreset), and, for the shared road, as an arena group of the
server with three cars (the path where only the car that ended restarts). Each run feeds a
SHA-256 of everything an agent receives: observations, rewards, both flags and the whole info
(action mask, applied action, reward terms, episode metrics). Variants switch on what the
defaults leave quiet: short episodes (truncation and autoreset; random weaving also crashes),
the lane-change check and the remembered cruise target, an RGB camera, and a LIDAR-only car.

A refactoring must leave every digest unchanged. A change of behaviour changes them: it
belongs in its own commit, which states why and records the new digests (run with
``OVERTAKE_GOLDEN_PRINT=1`` to print them). The digests are of float64 arithmetic through
numpy's ufuncs, recorded with numpy 2.4 on x86-64: another numpy release or CPU may round a
transcendental function differently, and then every digest differs at once.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest

from overtake.protocol.messages import Actions
from overtake.server.engine.env import HighwayEnv, HighwayVectorEnv
from overtake.server.service.groups import Group
from overtake.server.sim import PRESETS
from overtake.server.sim.sensors.kinematics import FEATURES as KINEMATICS_FEATURES
from overtake.server.sim.settings_history import BEFORE_AUTHORS_TRAFFIC

DENSITIES = ("light", "medium", "heavy")
ACTION_COUNT = 5
# Short episodes, so that every run crosses episode ends and autoresets.
SHORT = {"episode.max_decisions": 40}
# Each preset's variants: its own settings, and the others its options allow.
VARIANTS: dict[str, dict[str, dict[str, Any]]] = {
    "min2018": {
        "default": {},
        "short": SHORT,
        # Random weaving collides with the lane-change check off: terminations and reward.
        "unchecked": {**SHORT, "ego.lane_change_check": False},
        # The other settings of driver assistance and the cruise actions.
        "masked": {**SHORT, "ego.mask_refusals": True},
        "remembered": {**SHORT, "ego.cruise_mode": "remembered"},
        "rgb": {"camera.rgb": True, "camera.width_px": 40, "camera.height_px": 30, **SHORT},
        "lidar-only": {"camera.enabled": False, **SHORT},
        # The preset before the authors' traffic (issue 44): its digests are the default's then.
        "before44": BEFORE_AUTHORS_TRAFFIC["min2018"],
        # The treadmill the preset drove on before its authors' spawners (issue 68): its
        # digests are the default's then, so that the traffic's coming and going is all that
        # issue changed.
        "treadmill": {"traffic.entry": "comfortable"},
    },
    "fayjie2018": {
        "default": {},
        "short": SHORT,
        # A smaller map and camera, and the LIDAR's rays beside them.
        "small": {
            **SHORT,
            "lidar_map.cells": 20,
            "camera.width_px": 40,
            "camera.height_px": 30,
            "lidar.enabled": True,
            "lidar.ray_count": 90,
        },
    },
    "ho2018": {
        "default": {},
        "short": SHORT,
        # The thesis' Table 3 for the skipped frames instead of his code's repetition.
        "table3": {**SHORT, "ego.skipped_frames": "table3"},
        # Lane changes not checked: the only way to collide in Ho's world (rarely, at random).
        "unchecked": {**SHORT, "ego.lane_change_check": False},
        # A Boolean grid (off-road cells 0) with the LIDAR beside it.
        "lidar": {**SHORT, "grid.off_road_value": 0, "lidar.enabled": True, "lidar.ray_count": 90},
        # The preset before his traffic (issue 44): its digests are the default's then.
        "before44": BEFORE_AUTHORS_TRAFFIC["ho2018"],
        # Emergency brakes counted as every preset counted them before issue 56 (a deliberate
        # brake with a slower car ahead): its digests are the short variant's then, so that
        # the count is all that issue changed (the action applied as chosen, as then).
        "deliberate": {
            **SHORT,
            "ego.emergency_brake_count": "deliberate",
            "ego.applied_as_driven": False,
        },
        # The action applied as chosen, as before issue 66 (which applies it as his car drove
        # it and repeats that over the skipped frames): its digests are the short variant's
        # then, so that the setting is all that issue changed.
        "as-chosen": {**SHORT, "ego.applied_as_driven": False},
    },
    # highway-env's scenes (issue 57): their own episodes of 30 / 40 decisions end in crashes
    # and truncations; every Kinematics feature, absolute, seeing behind; every pair of cars
    # tested for collisions in the fast scene.
    "highway-fast": {
        "default": {},
        "features": {
            "kinematics.features": list(KINEMATICS_FEATURES),
            "kinematics.absolute": True,
            "kinematics.see_behind": True,
            "kinematics.vehicles_count": 8,
        },
        "all-pairs": {"highway_scene.collisions": "all"},
        # The action mask from the lane the car is changing into, as before issue 68: its
        # digests are all-pairs' then, so that the setting is all that issue changed.
        "target-mask": {
            "highway_scene.collisions": "all",
            "highway_scene.action_mask_lane": "target",
        },
    },
    "highway": {"default": {}, "unnormalised": {"kinematics.normalize": False}},
}
SINGLE_STEPS = 120
VECTOR_ARENAS, VECTOR_STEPS = 3, 90
GROUP_AGENTS, GROUP_STEPS = 3, 90


class Digest:
    """SHA-256 over arrays and nested mappings, in a canonical order (keys sorted)."""

    def __init__(self) -> None:
        self._hash = hashlib.sha256()

    def add(self, value: Any) -> None:
        if isinstance(value, Mapping):
            for key in sorted(value):
                self._hash.update(f"<{key}>".encode())
                self.add(value[key])
            return
        array = np.asarray(value)
        self._hash.update(f"{array.dtype.str}{array.shape}".encode())
        self._hash.update(np.ascontiguousarray(array).tobytes())

    def hexdigest(self) -> str:
        return self._hash.hexdigest()[:16]


def _single(preset: str, overrides: dict[str, Any]) -> str:
    env = HighwayEnv(preset=preset, overrides=overrides)
    rng = np.random.default_rng(11)
    digest = Digest()
    obs, info = env.reset(seed=5)
    digest.add({"obs": obs, "info": _without_counts(info)})
    episode = 0
    for _ in range(SINGLE_STEPS):
        obs, reward, terminated, truncated, info = env.step(int(rng.integers(ACTION_COUNT)))
        digest.add(
            {
                "obs": obs,
                "reward": reward,
                "terminated": terminated,
                "truncated": truncated,
                "info": _without_counts(info),
            }
        )
        if terminated or truncated:
            episode += 1
            obs, info = env.reset(seed=5 + 100 * episode if episode % 2 else None)
            digest.add({"obs": obs, "info": _without_counts(info)})
    return digest.hexdigest()


def _without_counts(info: dict[str, Any]) -> dict[str, Any]:
    """The info as the digests were recorded: the episode counts so far (issue 38 in the
    vector environment, issue 45 in all) are the metrics' own counts, checked against them
    here instead (where an episode ended: a vector env's ``_metrics``, a single one's all)."""
    counts = info.pop("episode_counts")
    if "metrics" in info:
        ended = info.get("_metrics", True)
        for name in counts:
            assert np.array_equal(
                np.asarray(counts[name])[ended], np.asarray(info["metrics"][name])[ended]
            )
    return info


def _vector(preset: str, overrides: dict[str, Any]) -> str:
    envs = HighwayVectorEnv(num_envs=VECTOR_ARENAS, preset=preset, overrides=overrides)
    rng = np.random.default_rng(12)
    digest = Digest()
    obs, info = envs.reset(seed=7)
    digest.add({"obs": obs, "info": _without_counts(info)})
    for _ in range(VECTOR_STEPS):
        actions = rng.integers(ACTION_COUNT, size=VECTOR_ARENAS)
        obs, reward, terminated, truncated, info = envs.step(actions)
        info = _without_counts(info)
        digest.add(
            {
                "obs": obs,
                "reward": reward,
                "terminated": terminated,
                "truncated": truncated,
                "info": info,
            }
        )
    return digest.hexdigest()


def _group(preset: str, overrides: dict[str, Any]) -> str:
    """A shared road: trainer a drives two cars of each of 2 arenas, b joins one car later."""
    group = Group.open(0, "golden", [0, 1], preset, overrides, GROUP_AGENTS, seed=3)
    for arena in range(2):
        group.claim("a", arena, 2, fresh=True)
    rng = np.random.default_rng(13)
    digest = Digest()
    for round_ in range(GROUP_STEPS):
        if round_ == 10:
            group.claim("b", 1, 1, fresh=False)
        for trainer, member in group.members.items():
            agents = np.flatnonzero(member.slots).astype(np.int32)
            group.accept(
                Actions(
                    trainer=trainer,
                    ticket=member.ticket,
                    group=0,
                    round=group.round,
                    agents=agents,
                    actions=rng.integers(ACTION_COUNT, size=agents.size),
                ),
                deadline_s=60.0,
            )
        for trainer, steps in sorted(group.step().items()):
            digest.add(
                {
                    "trainer": np.frombuffer(trainer.encode(), dtype=np.uint8),
                    "agents": steps.agents,
                    "obs": steps.observations,
                    "reward": steps.reward,
                    "terminated": steps.terminated,
                    "truncated": steps.truncated,
                    "applied": steps.action_applied,
                    "mask": steps.action_mask,
                    "terms": steps.reward_terms,
                    "metrics": steps.metrics,
                }
            )
    return digest.hexdigest()


RUNNERS = {"single": _single, "vector": _vector, "group": _group}

# (preset, density, variant, runner) -> digest. Recorded again for issue 44: min2018 with the
# authors' traffic (speeds stepping towards 80 km/h, random lane changes every 7.5 s on
# average, 100 m kept), their lane-change check and their 2,600 m episodes; ho2018 with his
# traffic (entry by free zones, his speed steps, holding and wandering speeds, the lane
# switcher's changes), his safety gaps, lane changes within a frame and his grid's cells.
# fayjie2018's are those of issue 32, but for the nine vector and group runs recorded again
# when the collision test began to run every frame in every arena (it had waited for a negative
# gap somewhere in the batch, and so saw some of these cars' collisions a decision late); each
# preset's "before44" is its default of then (BEFORE_AUTHORS_TRAFFIC). ho2018's recorded
# again for issue 66, where the action applied became his car's (ego.applied_as_driven: behind a
# car within the safety gap accelerate is keep, and with a slower car there the action is
# decelerate, repeated over the skipped frames): the runs where that happened (every group run,
# table3's and one unchecked single) changed; "as-chosen" (the setting off) holds the short
# variant's digests of before, and "before44" and "deliberate" turn it off and keep theirs.
# highway-fast's medium all-pairs group run recorded again for issue 68, where the action mask
# of highway-env's scene began to offer lane changes from the lane the car is in, as
# highway-env's get_available_actions does, not from the lane it is changing into: in round 57
# a car crashed in the middle of a lane change, and the mask sent with its last step no longer
# offers a change to the left (nothing else differs: what the cars did, the actions applied);
# "target-mask" (the setting as before) holds all-pairs' digests of before.
# min2018's recorded again for issue 68, where its traffic became its authors' spawners (the
# road starts empty, eight spawners bring cars 70% ahead on their timing, a car leaves beyond
# 100 m in a straight line or when it touches another, nothing is recycled): every min2018 run
# changed but "before44" and the new "treadmill" (traffic.entry "comfortable"), which hold the
# default's digests of before, so that the traffic's coming and going is all that changed.
# fayjie2018's traffic stays on the treadmill: its digests are unchanged.
GOLDEN: dict[tuple[str, str, str, str], str] = {
    ("min2018", "light", "default", "single"): "caf6159e516d86e2",
    ("min2018", "light", "default", "vector"): "5363b5497b33e322",
    ("min2018", "light", "default", "group"): "6fe437a39e806ce8",
    ("min2018", "light", "short", "single"): "7817c2a1859c4af6",
    ("min2018", "light", "short", "vector"): "2a87c7b291a25e83",
    ("min2018", "light", "short", "group"): "ed6ed9c35fc6dd27",
    ("min2018", "light", "unchecked", "single"): "7817c2a1859c4af6",
    ("min2018", "light", "unchecked", "vector"): "957e3dd76b7eb017",
    ("min2018", "light", "unchecked", "group"): "e8ccb91d7f3b6b44",
    ("min2018", "light", "masked", "single"): "7817c2a1859c4af6",
    ("min2018", "light", "masked", "vector"): "f3c7bdb5f14f1ac7",
    ("min2018", "light", "masked", "group"): "0c6379f11fef0a8e",
    ("min2018", "light", "remembered", "single"): "8e50fd6692150b83",
    ("min2018", "light", "remembered", "vector"): "d4c5f7431c646ca7",
    ("min2018", "light", "remembered", "group"): "da3df2c8a3d0c2cc",
    ("min2018", "light", "rgb", "single"): "cdb317c76586d613",
    ("min2018", "light", "rgb", "vector"): "7b4a7f6e07c30d0d",
    ("min2018", "light", "rgb", "group"): "50ed13adba94a84c",
    ("min2018", "light", "lidar-only", "single"): "4efa7adbbd2a65d8",
    ("min2018", "light", "lidar-only", "vector"): "9eea49bb5da5af7b",
    ("min2018", "light", "lidar-only", "group"): "6c44b4897b1cd151",
    ("min2018", "light", "before44", "single"): "de5b620b104d923c",
    ("min2018", "light", "before44", "vector"): "5433909a69499145",
    ("min2018", "light", "before44", "group"): "f6c1520525a3db41",
    ("min2018", "light", "treadmill", "single"): "ba0032c6c3ee6052",
    ("min2018", "light", "treadmill", "vector"): "95f3c78ffa9503f8",
    ("min2018", "light", "treadmill", "group"): "1a7eb36e091745a8",
    ("min2018", "medium", "default", "single"): "44fa03ff979309d0",
    ("min2018", "medium", "default", "vector"): "4f3c7834d1b86ee9",
    ("min2018", "medium", "default", "group"): "63a1f5e1029a4a1f",
    ("min2018", "medium", "short", "single"): "6d1e86b507b9e31a",
    ("min2018", "medium", "short", "vector"): "68df63557bd05099",
    ("min2018", "medium", "short", "group"): "46670b5779b067c5",
    ("min2018", "medium", "unchecked", "single"): "6d1e86b507b9e31a",
    ("min2018", "medium", "unchecked", "vector"): "094920205634b70b",
    ("min2018", "medium", "unchecked", "group"): "fef98ed4fbdfec26",
    ("min2018", "medium", "masked", "single"): "bfbed42117e1360b",
    ("min2018", "medium", "masked", "vector"): "f068dffafa75564b",
    ("min2018", "medium", "masked", "group"): "b9598591c0104232",
    ("min2018", "medium", "remembered", "single"): "0a42ca6adce5708d",
    ("min2018", "medium", "remembered", "vector"): "4269a0335a0066a4",
    ("min2018", "medium", "remembered", "group"): "a968766951760267",
    ("min2018", "medium", "rgb", "single"): "3ffb43e933a165c0",
    ("min2018", "medium", "rgb", "vector"): "3fc581ef8d94d43a",
    ("min2018", "medium", "rgb", "group"): "e5bd63d694f14359",
    ("min2018", "medium", "lidar-only", "single"): "9a20b4c2724a4fdb",
    ("min2018", "medium", "lidar-only", "vector"): "846a5f028c0934d6",
    ("min2018", "medium", "lidar-only", "group"): "5ab1c7b8c9d13479",
    ("min2018", "medium", "before44", "single"): "8cd460c6a3069621",
    ("min2018", "medium", "before44", "vector"): "1485367c969945bf",
    ("min2018", "medium", "before44", "group"): "4c1272d8a75bfc18",
    ("min2018", "medium", "treadmill", "single"): "9449e1c858721826",
    ("min2018", "medium", "treadmill", "vector"): "5988523b9e4bd7fd",
    ("min2018", "medium", "treadmill", "group"): "ef006740b72d0726",
    ("min2018", "heavy", "default", "single"): "3e4b57d4f4a7a3cc",
    ("min2018", "heavy", "default", "vector"): "8154553cb169451a",
    ("min2018", "heavy", "default", "group"): "a80d2c65cdcc902f",
    ("min2018", "heavy", "short", "single"): "ac4fd0d3766a4745",
    ("min2018", "heavy", "short", "vector"): "82693a452d892a58",
    ("min2018", "heavy", "short", "group"): "964069072ca148ad",
    ("min2018", "heavy", "unchecked", "single"): "a37a2692936a72f4",
    ("min2018", "heavy", "unchecked", "vector"): "3ab20d921daa34e9",
    ("min2018", "heavy", "unchecked", "group"): "febf2804893e3b4f",
    ("min2018", "heavy", "masked", "single"): "728d3a2c715577d1",
    ("min2018", "heavy", "masked", "vector"): "3ee1089445e35141",
    ("min2018", "heavy", "masked", "group"): "c612a0dc44c47269",
    ("min2018", "heavy", "remembered", "single"): "01149e79893cd2f1",
    ("min2018", "heavy", "remembered", "vector"): "2ea6bad290dc6875",
    ("min2018", "heavy", "remembered", "group"): "9ed61915d11972e9",
    ("min2018", "heavy", "rgb", "single"): "9d9f38de266c7c5c",
    ("min2018", "heavy", "rgb", "vector"): "b3960332ba94bddb",
    ("min2018", "heavy", "rgb", "group"): "757981ff6cd24ec0",
    ("min2018", "heavy", "lidar-only", "single"): "79db6b6743ddda2d",
    ("min2018", "heavy", "lidar-only", "vector"): "8ba28c86005bdca2",
    ("min2018", "heavy", "lidar-only", "group"): "e75616b495da320b",
    ("min2018", "heavy", "before44", "single"): "139ee3fc822eff47",
    ("min2018", "heavy", "before44", "vector"): "de52e494adbb09ee",
    ("min2018", "heavy", "before44", "group"): "26e5135e1c5276e5",
    ("min2018", "heavy", "treadmill", "single"): "fcb93726acfe1d16",
    ("min2018", "heavy", "treadmill", "vector"): "1b17dc8fbc71057f",
    ("min2018", "heavy", "treadmill", "group"): "37043859f6986b8b",
    ("fayjie2018", "light", "default", "single"): "d9b6e4a74e837310",
    ("fayjie2018", "light", "default", "vector"): "31020870c6f93bdf",
    ("fayjie2018", "light", "default", "group"): "b3da7ee6365a720a",
    ("fayjie2018", "light", "short", "single"): "e868dc94c92bf428",
    ("fayjie2018", "light", "short", "vector"): "80e68ca40e243ae2",
    ("fayjie2018", "light", "short", "group"): "ad00ad01844dbfaf",
    ("fayjie2018", "light", "small", "single"): "bdf33712c57486b8",
    ("fayjie2018", "light", "small", "vector"): "4a748db0790f9226",
    ("fayjie2018", "light", "small", "group"): "969b6c76764ef3d5",
    ("fayjie2018", "medium", "default", "single"): "c6f494ce610ff2e7",
    ("fayjie2018", "medium", "default", "vector"): "8e84f06ba5e483f5",
    ("fayjie2018", "medium", "default", "group"): "e0b5bce9882f3c95",
    ("fayjie2018", "medium", "short", "single"): "6d43cd3cb847fb3a",
    ("fayjie2018", "medium", "short", "vector"): "ebc884c1f43b0e0a",
    ("fayjie2018", "medium", "short", "group"): "632a5ce856b21a40",
    ("fayjie2018", "medium", "small", "single"): "41d78dd5818c03ab",
    ("fayjie2018", "medium", "small", "vector"): "3f47afa49627337b",
    ("fayjie2018", "medium", "small", "group"): "48c5b7ae86ba54fb",
    ("fayjie2018", "heavy", "default", "single"): "2481185d62f3675d",
    ("fayjie2018", "heavy", "default", "vector"): "3abc95485b73ad3a",
    ("fayjie2018", "heavy", "default", "group"): "c7c45079576fb2e4",
    ("fayjie2018", "heavy", "short", "single"): "0e33f9a35d66df6d",
    ("fayjie2018", "heavy", "short", "vector"): "3abc95485b73ad3a",
    ("fayjie2018", "heavy", "short", "group"): "cbdaa20708b03e00",
    ("fayjie2018", "heavy", "small", "single"): "0ad728d355a5d06a",
    ("fayjie2018", "heavy", "small", "vector"): "ef539f70f052c2d5",
    ("fayjie2018", "heavy", "small", "group"): "1e122c9edcf28165",
    ("ho2018", "light", "default", "single"): "b53fccf1bb78cb4b",
    ("ho2018", "light", "default", "vector"): "1c9e0448e617da91",
    ("ho2018", "light", "default", "group"): "8606e230709bd414",
    ("ho2018", "light", "short", "single"): "e20caf8dc26ca581",
    ("ho2018", "light", "short", "vector"): "1d3033f6d6e568ae",
    ("ho2018", "light", "short", "group"): "594f06d17e0e9848",
    ("ho2018", "light", "table3", "single"): "5fe8ffb6cf839c47",
    ("ho2018", "light", "table3", "vector"): "2f3ee9a483d5cfd7",
    ("ho2018", "light", "table3", "group"): "b867d909ef9790db",
    ("ho2018", "light", "unchecked", "single"): "11f07510074915f0",
    ("ho2018", "light", "unchecked", "vector"): "e11a302e97ca78c0",
    ("ho2018", "light", "unchecked", "group"): "ea8dfe6f57160371",
    ("ho2018", "light", "lidar", "single"): "5aa23d3dffbb7ab6",
    ("ho2018", "light", "lidar", "vector"): "014ab20ae497298b",
    ("ho2018", "light", "lidar", "group"): "e19395e7d0a6ff33",
    ("ho2018", "light", "before44", "single"): "075dcf16a4275bab",
    ("ho2018", "light", "before44", "vector"): "d17feef6606b1ecc",
    ("ho2018", "light", "before44", "group"): "12fc1d15a63d35b5",
    ("ho2018", "light", "deliberate", "single"): "14f09350859ffb18",
    ("ho2018", "light", "deliberate", "vector"): "935fb506321ac915",
    ("ho2018", "light", "deliberate", "group"): "b7c5a18692c72578",
    ("ho2018", "light", "as-chosen", "single"): "e20caf8dc26ca581",
    ("ho2018", "light", "as-chosen", "vector"): "1d3033f6d6e568ae",
    ("ho2018", "light", "as-chosen", "group"): "45aa40222816596e",
    ("ho2018", "medium", "default", "single"): "230e50f62d6feefc",
    ("ho2018", "medium", "default", "vector"): "9729f94591028986",
    ("ho2018", "medium", "default", "group"): "d2100040f33acf7c",
    ("ho2018", "medium", "short", "single"): "eadd3735bb2015da",
    ("ho2018", "medium", "short", "vector"): "965fd400d3dae376",
    ("ho2018", "medium", "short", "group"): "cff8b88e65da50fd",
    ("ho2018", "medium", "table3", "single"): "7d764cba57a51ca5",
    ("ho2018", "medium", "table3", "vector"): "267cf13c775e73c5",
    ("ho2018", "medium", "table3", "group"): "5570eaa2e1d04375",
    ("ho2018", "medium", "unchecked", "single"): "0fb86458f03210d2",
    ("ho2018", "medium", "unchecked", "vector"): "41e636b24922d2bc",
    ("ho2018", "medium", "unchecked", "group"): "8eb7c83bb6b1b97d",
    ("ho2018", "medium", "lidar", "single"): "f80e1627466d4fd7",
    ("ho2018", "medium", "lidar", "vector"): "2a8ed666be15e68f",
    ("ho2018", "medium", "lidar", "group"): "63d7d2c98301cf20",
    ("ho2018", "medium", "before44", "single"): "1769b3e47cd31dc1",
    ("ho2018", "medium", "before44", "vector"): "12e3bd5aa40c23b6",
    ("ho2018", "medium", "before44", "group"): "b707ff12fb0c7a27",
    ("ho2018", "medium", "deliberate", "single"): "eadd3735bb2015da",
    ("ho2018", "medium", "deliberate", "vector"): "6e799d9ca2303216",
    ("ho2018", "medium", "deliberate", "group"): "e210b0c66e8e8917",
    ("ho2018", "medium", "as-chosen", "single"): "eadd3735bb2015da",
    ("ho2018", "medium", "as-chosen", "vector"): "965fd400d3dae376",
    ("ho2018", "medium", "as-chosen", "group"): "c485ba2875d060b3",
    ("ho2018", "heavy", "default", "single"): "c8f15d202e7a7c14",
    ("ho2018", "heavy", "default", "vector"): "5f52dca0f13fe2d2",
    ("ho2018", "heavy", "default", "group"): "396dc544172ae48d",
    ("ho2018", "heavy", "short", "single"): "d255d81d1c856531",
    ("ho2018", "heavy", "short", "vector"): "986a8eae0a605ca9",
    ("ho2018", "heavy", "short", "group"): "bf27da2e40afb262",
    ("ho2018", "heavy", "table3", "single"): "817b41d494ba0347",
    ("ho2018", "heavy", "table3", "vector"): "4533dd7f20867ba7",
    ("ho2018", "heavy", "table3", "group"): "d6d5803cb67a776c",
    ("ho2018", "heavy", "unchecked", "single"): "ae3898107b13f81d",
    ("ho2018", "heavy", "unchecked", "vector"): "0cd33afe8ee1e20f",
    ("ho2018", "heavy", "unchecked", "group"): "eec926ac7053f661",
    ("ho2018", "heavy", "lidar", "single"): "efe59938f138a48e",
    ("ho2018", "heavy", "lidar", "vector"): "b5eb43eda7d375e2",
    ("ho2018", "heavy", "lidar", "group"): "ba2772ecbcd64c96",
    ("ho2018", "heavy", "before44", "single"): "b24c493ece4dc1bf",
    ("ho2018", "heavy", "before44", "vector"): "1021a52d61ce612a",
    ("ho2018", "heavy", "before44", "group"): "0a8eae4c40fc2001",
    ("ho2018", "heavy", "deliberate", "single"): "434663e11d0292b2",
    ("ho2018", "heavy", "deliberate", "vector"): "02393eebcb599968",
    ("ho2018", "heavy", "deliberate", "group"): "dab369f0e083fd74",
    ("ho2018", "heavy", "as-chosen", "single"): "d255d81d1c856531",
    ("ho2018", "heavy", "as-chosen", "vector"): "986a8eae0a605ca9",
    ("ho2018", "heavy", "as-chosen", "group"): "535e187a52502784",
    ("highway", "light", "default", "single"): "586738687e4d599d",
    ("highway", "light", "default", "vector"): "421f4be563dda879",
    ("highway", "light", "default", "group"): "cf781e937f921f28",
    ("highway", "light", "unnormalised", "single"): "1a6ef7f6b0035bda",
    ("highway", "light", "unnormalised", "vector"): "069ac79572df6b24",
    ("highway", "light", "unnormalised", "group"): "bb67ffb8d6fda0f4",
    ("highway", "medium", "default", "single"): "9426a18e9475e93b",
    ("highway", "medium", "default", "vector"): "e8c54c8aa63965f1",
    ("highway", "medium", "default", "group"): "ffacf9e727f985e9",
    ("highway", "medium", "unnormalised", "single"): "4e8394e7ea933b55",
    ("highway", "medium", "unnormalised", "vector"): "e9acdfdc08fed184",
    ("highway", "medium", "unnormalised", "group"): "f6e1f111fd588e37",
    ("highway", "heavy", "default", "single"): "359679b8e78bc978",
    ("highway", "heavy", "default", "vector"): "d2af86ec4a82fe7c",
    ("highway", "heavy", "default", "group"): "698bcdee59173322",
    ("highway", "heavy", "unnormalised", "single"): "f182d1da503fb153",
    ("highway", "heavy", "unnormalised", "vector"): "84a29078b3b42465",
    ("highway", "heavy", "unnormalised", "group"): "d219cb5412d4a196",
    ("highway-fast", "light", "default", "single"): "12f4912d6078a19f",
    ("highway-fast", "light", "default", "vector"): "eaafdce46e8086f8",
    ("highway-fast", "light", "default", "group"): "b42ebeed9da1780e",
    ("highway-fast", "light", "features", "single"): "d5289321b0f76fe0",
    ("highway-fast", "light", "features", "vector"): "5e61e8a8bf14a914",
    ("highway-fast", "light", "features", "group"): "3c6848f9efd2aa8e",
    ("highway-fast", "light", "all-pairs", "single"): "12f4912d6078a19f",
    ("highway-fast", "light", "all-pairs", "vector"): "eaafdce46e8086f8",
    ("highway-fast", "light", "all-pairs", "group"): "b42ebeed9da1780e",
    ("highway-fast", "medium", "default", "single"): "20f780f8fb37fe7e",
    ("highway-fast", "medium", "default", "vector"): "64a5a7a562d7628b",
    ("highway-fast", "medium", "default", "group"): "2c8a74ce52b2dab6",
    ("highway-fast", "medium", "features", "single"): "7f663a2b092b8ad6",
    ("highway-fast", "medium", "features", "vector"): "34268789644444b3",
    ("highway-fast", "medium", "features", "group"): "aead3d04d9042457",
    ("highway-fast", "medium", "all-pairs", "single"): "20f780f8fb37fe7e",
    ("highway-fast", "medium", "all-pairs", "vector"): "64a5a7a562d7628b",
    ("highway-fast", "medium", "all-pairs", "group"): "a0b0d3a6a5b2879d",
    ("highway-fast", "heavy", "default", "single"): "a8bbf60bac8301c5",
    ("highway-fast", "heavy", "default", "vector"): "57d10529917cd1d2",
    ("highway-fast", "heavy", "default", "group"): "d34a3f32e3d4aeff",
    ("highway-fast", "heavy", "features", "single"): "6959e26c4a48b8eb",
    ("highway-fast", "heavy", "features", "vector"): "ed8894242d2be73c",
    ("highway-fast", "heavy", "features", "group"): "1c2948a47ecfa363",
    ("highway-fast", "heavy", "all-pairs", "single"): "a8bbf60bac8301c5",
    ("highway-fast", "heavy", "all-pairs", "vector"): "57d10529917cd1d2",
    ("highway-fast", "heavy", "all-pairs", "group"): "d34a3f32e3d4aeff",
    ("highway-fast", "light", "target-mask", "single"): "12f4912d6078a19f",
    ("highway-fast", "light", "target-mask", "vector"): "eaafdce46e8086f8",
    ("highway-fast", "light", "target-mask", "group"): "b42ebeed9da1780e",
    ("highway-fast", "medium", "target-mask", "single"): "20f780f8fb37fe7e",
    ("highway-fast", "medium", "target-mask", "vector"): "64a5a7a562d7628b",
    ("highway-fast", "medium", "target-mask", "group"): "fdb8d8e38b1a4411",
    ("highway-fast", "heavy", "target-mask", "single"): "a8bbf60bac8301c5",
    ("highway-fast", "heavy", "target-mask", "vector"): "57d10529917cd1d2",
    ("highway-fast", "heavy", "target-mask", "group"): "d34a3f32e3d4aeff",
}


def _cases() -> list[tuple[str, str, str, str]]:
    return [
        (preset, density, variant, runner)
        for preset in sorted(PRESETS)
        for density in DENSITIES
        for variant in VARIANTS.get(preset, {"default": {}})
        for runner in RUNNERS
    ]


def test_every_preset_has_its_variants():
    assert sorted(VARIANTS) == sorted(PRESETS)


@pytest.mark.parametrize("preset,density,variant,runner", _cases())
def test_trajectory_matches_its_golden_digest(preset, density, variant, runner):
    overrides = {"traffic.density": density, **VARIANTS[preset][variant]}
    digest = RUNNERS[runner](preset, overrides)
    key = (preset, density, variant, runner)
    if os.environ.get("OVERTAKE_GOLDEN_PRINT"):
        print(f"\n    {key!r}: {digest!r},")
    assert key in GOLDEN, f"no golden digest for {key}: record one (OVERTAKE_GOLDEN_PRINT=1)"
    assert digest == GOLDEN[key], (
        f"{key} stepped differently from its golden run: digest {digest}, recorded {GOLDEN[key]}"
    )


def test_the_golden_cases_cover_collisions_and_episode_ends():
    """The variants exercise what they are there for (else a digest guards nothing). Ho's
    world hardly collides even unchecked (tests/papers/test_ho2018.py scripts a collision there);
    min2018's since its authors' spawners (issue 68) less than on the treadmill (the road starts
    empty and holds fewer cars): its unchecked vector runs collide in medium traffic."""
    terminated_total = truncated_total = 0
    for density in DENSITIES:
        envs = HighwayVectorEnv(
            num_envs=VECTOR_ARENAS,
            overrides={"traffic.density": density, **VARIANTS["min2018"]["unchecked"]},
        )
        rng = np.random.default_rng(12)
        envs.reset(seed=7)
        for _ in range(VECTOR_STEPS):
            actions = rng.integers(ACTION_COUNT, size=VECTOR_ARENAS)
            _, _, terminated, truncated, _ = envs.step(actions)
            terminated_total += int(terminated.sum())
            truncated_total += int(truncated.sum())
        envs.close()
    assert terminated_total >= 1 and truncated_total >= 1

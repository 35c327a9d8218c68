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
from overtake.server.env import HighwayEnv, HighwayVectorEnv
from overtake.server.groups import Group
from overtake.server.sim import PRESETS

DENSITIES = ("light", "medium", "heavy")
ACTION_COUNT = 5
# Short episodes, so that every run crosses episode ends and autoresets.
SHORT = {"episode.max_decisions": 40}
# Each preset's variants: its own settings, and the others its options allow.
VARIANTS: dict[str, dict[str, dict[str, Any]]] = {
    "min2018": {
        "default": {},
        # Random weaving collides (no lane-change check in min2018): terminations and reward.
        "short": SHORT,
        # The other settings of driver assistance and the cruise actions.
        "checked": {**SHORT, "ego.lane_change_check": True},
        "remembered": {**SHORT, "ego.cruise_mode": "remembered"},
        "rgb": {"camera.rgb": True, "camera.width_px": 40, "camera.height_px": 30, **SHORT},
        "lidar-only": {"camera.enabled": False, **SHORT},
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
        # His code's rule for the skipped frames instead of the thesis' Table 3.
        "repeat": {**SHORT, "ego.skipped_frames": "repeat"},
        # Lane changes not checked: the only way to collide in Ho's world (rarely, at random).
        "unchecked": {**SHORT, "ego.lane_change_check": False},
        # A Boolean grid (off-road cells 0) with the LIDAR beside it.
        "lidar": {**SHORT, "grid.off_road_value": 0, "lidar.enabled": True, "lidar.ray_count": 90},
    },
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
    digest.add({"obs": obs, "info": info})
    episode = 0
    for _ in range(SINGLE_STEPS):
        obs, reward, terminated, truncated, info = env.step(int(rng.integers(ACTION_COUNT)))
        digest.add(
            {
                "obs": obs,
                "reward": reward,
                "terminated": terminated,
                "truncated": truncated,
                "info": info,
            }
        )
        if terminated or truncated:
            episode += 1
            obs, info = env.reset(seed=5 + 100 * episode if episode % 2 else None)
            digest.add({"obs": obs, "info": info})
    return digest.hexdigest()


def _vector(preset: str, overrides: dict[str, Any]) -> str:
    envs = HighwayVectorEnv(num_envs=VECTOR_ARENAS, preset=preset, overrides=overrides)
    rng = np.random.default_rng(12)
    digest = Digest()
    obs, info = envs.reset(seed=7)
    digest.add({"obs": obs, "info": info})
    for _ in range(VECTOR_STEPS):
        actions = rng.integers(ACTION_COUNT, size=VECTOR_ARENAS)
        obs, reward, terminated, truncated, info = envs.step(actions)
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

# (preset, density, variant, runner) -> digest. Recorded when min2018 became the paper's set-up
# (cruise actions from the current speed, warnings, random traffic; the split into rooms before
# it left every digest unchanged).
GOLDEN: dict[tuple[str, str, str, str], str] = {
    ("min2018", "light", "default", "single"): "70543af3bc532e2f",
    ("min2018", "light", "default", "vector"): "45a74c988101db5a",
    ("min2018", "light", "default", "group"): "f047a6cd8e62e35e",
    ("min2018", "light", "short", "single"): "0c91c7b238ca49aa",
    ("min2018", "light", "short", "vector"): "e3b8cf1076d4b37c",
    ("min2018", "light", "short", "group"): "5d1d252873e86fb6",
    ("min2018", "light", "checked", "single"): "f71005af4471bbd8",
    ("min2018", "light", "checked", "vector"): "fe307f72f00ee6e3",
    ("min2018", "light", "checked", "group"): "9735f518a07ccb2d",
    ("min2018", "light", "remembered", "single"): "b725d3f49a4188df",
    ("min2018", "light", "remembered", "vector"): "977c02dcab300042",
    ("min2018", "light", "remembered", "group"): "adfba46b89f0b0e8",
    ("min2018", "light", "rgb", "single"): "f31dcbc33605eab5",
    ("min2018", "light", "rgb", "vector"): "70254d7691197c03",
    ("min2018", "light", "rgb", "group"): "d2bafa360baa3bba",
    ("min2018", "light", "lidar-only", "single"): "1b8d69b3db1b4049",
    ("min2018", "light", "lidar-only", "vector"): "8cc17f61001ce6c4",
    ("min2018", "light", "lidar-only", "group"): "6f4439faa7a5b428",
    ("min2018", "medium", "default", "single"): "de5b620b104d923c",
    ("min2018", "medium", "default", "vector"): "5433909a69499145",
    ("min2018", "medium", "default", "group"): "f6c1520525a3db41",
    ("min2018", "medium", "short", "single"): "66ae79496c4504f1",
    ("min2018", "medium", "short", "vector"): "42f164633cdec614",
    ("min2018", "medium", "short", "group"): "6a75fcb51668ad00",
    ("min2018", "medium", "checked", "single"): "f62fe7f88362d909",
    ("min2018", "medium", "checked", "vector"): "99127ef2a81ec7b3",
    ("min2018", "medium", "checked", "group"): "7ad1ce487fed2b23",
    ("min2018", "medium", "remembered", "single"): "4be12585486272a7",
    ("min2018", "medium", "remembered", "vector"): "f080bfa92cfb253b",
    ("min2018", "medium", "remembered", "group"): "182f01c696de40fe",
    ("min2018", "medium", "rgb", "single"): "395f6f821bf4c2ff",
    ("min2018", "medium", "rgb", "vector"): "662fde8d763d8d61",
    ("min2018", "medium", "rgb", "group"): "4b4fc43fa7cc5181",
    ("min2018", "medium", "lidar-only", "single"): "1fbdde77c7e90868",
    ("min2018", "medium", "lidar-only", "vector"): "35b436ac84233f01",
    ("min2018", "medium", "lidar-only", "group"): "c5e4e97b55140c86",
    ("min2018", "heavy", "default", "single"): "8cd460c6a3069621",
    ("min2018", "heavy", "default", "vector"): "1485367c969945bf",
    ("min2018", "heavy", "default", "group"): "4c1272d8a75bfc18",
    ("min2018", "heavy", "short", "single"): "3b86bc19f60ca250",
    ("min2018", "heavy", "short", "vector"): "63559480e250d47b",
    ("min2018", "heavy", "short", "group"): "c2c6ca746ef9537c",
    ("min2018", "heavy", "checked", "single"): "4925b5d69b03b0b9",
    ("min2018", "heavy", "checked", "vector"): "8a94cc6b651130e8",
    ("min2018", "heavy", "checked", "group"): "efbb35c5f2fd717b",
    ("min2018", "heavy", "remembered", "single"): "b1f4b35caf6e6be0",
    ("min2018", "heavy", "remembered", "vector"): "e34f20a04cc55cc6",
    ("min2018", "heavy", "remembered", "group"): "471fefc2868dab0f",
    ("min2018", "heavy", "rgb", "single"): "05acc512e154ea53",
    ("min2018", "heavy", "rgb", "vector"): "4c0f43e265db41ba",
    ("min2018", "heavy", "rgb", "group"): "eec5418b2dd2a389",
    ("min2018", "heavy", "lidar-only", "single"): "e409045fb6a9169d",
    ("min2018", "heavy", "lidar-only", "vector"): "1ea32c31234bf4fb",
    ("min2018", "heavy", "lidar-only", "group"): "09a7dac495b06c42",
    # Recorded when fayjie2018 was added (issue 14).
    ("fayjie2018", "light", "default", "single"): "d9b6e4a74e837310",
    ("fayjie2018", "light", "default", "vector"): "31020870c6f93bdf",
    ("fayjie2018", "light", "default", "group"): "a9c02ef1213f6efa",
    ("fayjie2018", "light", "short", "single"): "e868dc94c92bf428",
    ("fayjie2018", "light", "short", "vector"): "80e68ca40e243ae2",
    ("fayjie2018", "light", "short", "group"): "49161dce934728de",
    ("fayjie2018", "light", "small", "single"): "bdf33712c57486b8",
    ("fayjie2018", "light", "small", "vector"): "4a748db0790f9226",
    ("fayjie2018", "light", "small", "group"): "bd58dab81ae357b4",
    ("fayjie2018", "medium", "default", "single"): "c6f494ce610ff2e7",
    ("fayjie2018", "medium", "default", "vector"): "8e84f06ba5e483f5",
    ("fayjie2018", "medium", "default", "group"): "59e314878cf5fc2d",
    ("fayjie2018", "medium", "short", "single"): "6d43cd3cb847fb3a",
    ("fayjie2018", "medium", "short", "vector"): "ebc884c1f43b0e0a",
    ("fayjie2018", "medium", "short", "group"): "156370aff9a6f229",
    ("fayjie2018", "medium", "small", "single"): "41d78dd5818c03ab",
    ("fayjie2018", "medium", "small", "vector"): "3f47afa49627337b",
    ("fayjie2018", "medium", "small", "group"): "71cc937b679f23bd",
    ("fayjie2018", "heavy", "default", "single"): "2481185d62f3675d",
    ("fayjie2018", "heavy", "default", "vector"): "6355582d725f32e5",
    ("fayjie2018", "heavy", "default", "group"): "84371342a09ac765",
    ("fayjie2018", "heavy", "short", "single"): "80c2bcb5d3506f4d",
    ("fayjie2018", "heavy", "short", "vector"): "3ed27b7aabec0fd4",
    ("fayjie2018", "heavy", "short", "group"): "c3b4c4c01c99fc7b",
    ("fayjie2018", "heavy", "small", "single"): "34d831bb01c12e79",
    ("fayjie2018", "heavy", "small", "vector"): "143398aa9e331b76",
    ("fayjie2018", "heavy", "small", "group"): "8994c686ab1abf23",
    # Recorded when ho2018 was added (issue 14).
    ("ho2018", "light", "default", "single"): "427fc030a78c5d4d",
    ("ho2018", "light", "default", "vector"): "aec90049cc88016e",
    ("ho2018", "light", "default", "group"): "63192aa60fa9b42f",
    ("ho2018", "light", "short", "single"): "4bb85221f287ad43",
    ("ho2018", "light", "short", "vector"): "dab6195720030ac3",
    ("ho2018", "light", "short", "group"): "41590881a3d897f1",
    ("ho2018", "light", "repeat", "single"): "dae1c366faa7338c",
    ("ho2018", "light", "repeat", "vector"): "61a5a185401aceca",
    ("ho2018", "light", "repeat", "group"): "6216a2dcd7569fec",
    ("ho2018", "light", "unchecked", "single"): "920c53b011917ec1",
    ("ho2018", "light", "unchecked", "vector"): "3bb089da8de82091",
    ("ho2018", "light", "unchecked", "group"): "e2e8f85afd6b9bd7",
    ("ho2018", "light", "lidar", "single"): "df92f9521e46dcd4",
    ("ho2018", "light", "lidar", "vector"): "d3bf479d14dc1906",
    ("ho2018", "light", "lidar", "group"): "e56c39d314d19a64",
    ("ho2018", "medium", "default", "single"): "e4f63f6f019583fd",
    ("ho2018", "medium", "default", "vector"): "58cd3f70d73fdbc5",
    ("ho2018", "medium", "default", "group"): "f4e149235d0e1477",
    ("ho2018", "medium", "short", "single"): "09fc9321a88b837f",
    ("ho2018", "medium", "short", "vector"): "48575d6212bf7744",
    ("ho2018", "medium", "short", "group"): "6416401094ef9feb",
    ("ho2018", "medium", "repeat", "single"): "8b6f664c5809e098",
    ("ho2018", "medium", "repeat", "vector"): "790f75175bed3803",
    ("ho2018", "medium", "repeat", "group"): "a8b7b21eb5bbf6f3",
    ("ho2018", "medium", "unchecked", "single"): "e3696fc86b14ab51",
    ("ho2018", "medium", "unchecked", "vector"): "41d4dc1fee12b0ae",
    ("ho2018", "medium", "unchecked", "group"): "8bd07cf829ace1a7",
    ("ho2018", "medium", "lidar", "single"): "1e794055df0e299d",
    ("ho2018", "medium", "lidar", "vector"): "95b5626e5133a4af",
    ("ho2018", "medium", "lidar", "group"): "2a53b762a929f3be",
    ("ho2018", "heavy", "default", "single"): "b4f4d08dc18dc29e",
    ("ho2018", "heavy", "default", "vector"): "cfa6e3f5f5a8058b",
    ("ho2018", "heavy", "default", "group"): "fae2eb56c77ce5e4",
    ("ho2018", "heavy", "short", "single"): "966a5f67667ee41d",
    ("ho2018", "heavy", "short", "vector"): "cb3e7df3d48647cb",
    ("ho2018", "heavy", "short", "group"): "9c3173ec79ead109",
    ("ho2018", "heavy", "repeat", "single"): "3ba58c2056d2f547",
    ("ho2018", "heavy", "repeat", "vector"): "e6fe541ffa9871cc",
    ("ho2018", "heavy", "repeat", "group"): "f844f7780d702f1d",
    ("ho2018", "heavy", "unchecked", "single"): "46e96690d770bd17",
    ("ho2018", "heavy", "unchecked", "vector"): "6b6b3537f33e94bf",
    ("ho2018", "heavy", "unchecked", "group"): "bc5b26272c7336c0",
    ("ho2018", "heavy", "lidar", "single"): "6deaff9a776cd660",
    ("ho2018", "heavy", "lidar", "vector"): "2a939b973370807e",
    ("ho2018", "heavy", "lidar", "group"): "4c44fca442ff0af6",
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
    world hardly collides even unchecked (tests/test_ho2018.py scripts a collision there)."""
    envs = HighwayVectorEnv(
        num_envs=VECTOR_ARENAS,
        overrides={"traffic.density": "heavy", **VARIANTS["min2018"]["short"]},
    )
    rng = np.random.default_rng(12)
    envs.reset(seed=7)
    terminated_total = truncated_total = 0
    for _ in range(VECTOR_STEPS):
        _, _, terminated, truncated, _ = envs.step(rng.integers(ACTION_COUNT, size=VECTOR_ARENAS))
        terminated_total += int(terminated.sum())
        truncated_total += int(truncated.sum())
    assert terminated_total >= 1 and truncated_total >= 1

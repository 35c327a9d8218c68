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
        # The thesis' Table 3 for the skipped frames instead of his code's repetition.
        "table3": {**SHORT, "ego.skipped_frames": "table3"},
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


def _without_counts(info: dict[str, Any]) -> dict[str, Any]:
    """The vector environments' info as the digests were recorded: the episode counts so far
    (issue 38) are the metrics' own counts, checked against them here instead."""
    counts = info.pop("episode_counts")
    for name, ended in ((name, info.get("_metrics")) for name in counts):
        if ended is not None:
            assert np.array_equal(counts[name][ended], info["metrics"][name][ended])
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

# (preset, density, variant, runner) -> digest. Recorded again for issue 32: ho2018 read from
# one scale of Ho's code (1 m boxes, 0.08 s frames, 7 m cars, his road window, repeated skipped
# frames); min2018's densities 10 / 20 / 32; and traffic's safety cap consistent with the
# trapezoid integration of positions (every preset where a follower closes in hard).
GOLDEN: dict[tuple[str, str, str, str], str] = {
    ("min2018", "light", "default", "single"): "de5b620b104d923c",
    ("min2018", "light", "default", "vector"): "5433909a69499145",
    ("min2018", "light", "default", "group"): "f6c1520525a3db41",
    ("min2018", "light", "short", "single"): "66ae79496c4504f1",
    ("min2018", "light", "short", "vector"): "42f164633cdec614",
    ("min2018", "light", "short", "group"): "6a75fcb51668ad00",
    ("min2018", "light", "checked", "single"): "f62fe7f88362d909",
    ("min2018", "light", "checked", "vector"): "99127ef2a81ec7b3",
    ("min2018", "light", "checked", "group"): "7ad1ce487fed2b23",
    ("min2018", "light", "remembered", "single"): "4be12585486272a7",
    ("min2018", "light", "remembered", "vector"): "f080bfa92cfb253b",
    ("min2018", "light", "remembered", "group"): "182f01c696de40fe",
    ("min2018", "light", "rgb", "single"): "395f6f821bf4c2ff",
    ("min2018", "light", "rgb", "vector"): "662fde8d763d8d61",
    ("min2018", "light", "rgb", "group"): "4b4fc43fa7cc5181",
    ("min2018", "light", "lidar-only", "single"): "1fbdde77c7e90868",
    ("min2018", "light", "lidar-only", "vector"): "35b436ac84233f01",
    ("min2018", "light", "lidar-only", "group"): "c5e4e97b55140c86",
    ("min2018", "medium", "default", "single"): "8cd460c6a3069621",
    ("min2018", "medium", "default", "vector"): "1485367c969945bf",
    ("min2018", "medium", "default", "group"): "4c1272d8a75bfc18",
    ("min2018", "medium", "short", "single"): "3b86bc19f60ca250",
    ("min2018", "medium", "short", "vector"): "63559480e250d47b",
    ("min2018", "medium", "short", "group"): "c2c6ca746ef9537c",
    ("min2018", "medium", "checked", "single"): "4925b5d69b03b0b9",
    ("min2018", "medium", "checked", "vector"): "8a94cc6b651130e8",
    ("min2018", "medium", "checked", "group"): "efbb35c5f2fd717b",
    ("min2018", "medium", "remembered", "single"): "b1f4b35caf6e6be0",
    ("min2018", "medium", "remembered", "vector"): "e34f20a04cc55cc6",
    ("min2018", "medium", "remembered", "group"): "471fefc2868dab0f",
    ("min2018", "medium", "rgb", "single"): "05acc512e154ea53",
    ("min2018", "medium", "rgb", "vector"): "4c0f43e265db41ba",
    ("min2018", "medium", "rgb", "group"): "eec5418b2dd2a389",
    ("min2018", "medium", "lidar-only", "single"): "e409045fb6a9169d",
    ("min2018", "medium", "lidar-only", "vector"): "1ea32c31234bf4fb",
    ("min2018", "medium", "lidar-only", "group"): "09a7dac495b06c42",
    ("min2018", "heavy", "default", "single"): "139ee3fc822eff47",
    ("min2018", "heavy", "default", "vector"): "de52e494adbb09ee",
    ("min2018", "heavy", "default", "group"): "26e5135e1c5276e5",
    ("min2018", "heavy", "short", "single"): "14924cf3200c3b9d",
    ("min2018", "heavy", "short", "vector"): "48f3d6352478e287",
    ("min2018", "heavy", "short", "group"): "bc28ab74c552854b",
    ("min2018", "heavy", "checked", "single"): "c38479ad66bb5ec9",
    ("min2018", "heavy", "checked", "vector"): "f3de2bf423370b3e",
    ("min2018", "heavy", "checked", "group"): "6dfc3bd412459a70",
    ("min2018", "heavy", "remembered", "single"): "4f32f286078e835a",
    ("min2018", "heavy", "remembered", "vector"): "9107550e3ecd5b78",
    ("min2018", "heavy", "remembered", "group"): "8c7e3eda193fff89",
    ("min2018", "heavy", "rgb", "single"): "30f8e948abf31e89",
    ("min2018", "heavy", "rgb", "vector"): "53b5fe62000704db",
    ("min2018", "heavy", "rgb", "group"): "fec10ce195e76ae8",
    ("min2018", "heavy", "lidar-only", "single"): "e36cca833016202d",
    ("min2018", "heavy", "lidar-only", "vector"): "e39b9f7112995412",
    ("min2018", "heavy", "lidar-only", "group"): "2ab8e5549db12c20",
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
    ("fayjie2018", "medium", "default", "group"): "99781ea408eab9d7",
    ("fayjie2018", "medium", "short", "single"): "6d43cd3cb847fb3a",
    ("fayjie2018", "medium", "short", "vector"): "ebc884c1f43b0e0a",
    ("fayjie2018", "medium", "short", "group"): "7d57fb3a02095e0a",
    ("fayjie2018", "medium", "small", "single"): "41d78dd5818c03ab",
    ("fayjie2018", "medium", "small", "vector"): "3f47afa49627337b",
    ("fayjie2018", "medium", "small", "group"): "c121a53c887586bf",
    ("fayjie2018", "heavy", "default", "single"): "2481185d62f3675d",
    ("fayjie2018", "heavy", "default", "vector"): "6355582d725f32e5",
    ("fayjie2018", "heavy", "default", "group"): "860227c295ffa410",
    ("fayjie2018", "heavy", "short", "single"): "0e33f9a35d66df6d",
    ("fayjie2018", "heavy", "short", "vector"): "a70cd60c178d6d65",
    ("fayjie2018", "heavy", "short", "group"): "c3b4c4c01c99fc7b",
    ("fayjie2018", "heavy", "small", "single"): "0ad728d355a5d06a",
    ("fayjie2018", "heavy", "small", "vector"): "3ff3533a46841e68",
    ("fayjie2018", "heavy", "small", "group"): "8994c686ab1abf23",
    ("ho2018", "light", "default", "single"): "075dcf16a4275bab",
    ("ho2018", "light", "default", "vector"): "d17feef6606b1ecc",
    ("ho2018", "light", "default", "group"): "12fc1d15a63d35b5",
    ("ho2018", "light", "short", "single"): "aa898db67443aa18",
    ("ho2018", "light", "short", "vector"): "d6197b5c2ff7d94c",
    ("ho2018", "light", "short", "group"): "19a2169e43fe7b3b",
    ("ho2018", "light", "table3", "single"): "763c1e06b227dbfa",
    ("ho2018", "light", "table3", "vector"): "f8b812a5a449cd0f",
    ("ho2018", "light", "table3", "group"): "085942f52bc29238",
    ("ho2018", "light", "unchecked", "single"): "8e99d4fa420ff7dc",
    ("ho2018", "light", "unchecked", "vector"): "72ae8d709d1e5223",
    ("ho2018", "light", "unchecked", "group"): "7c65ac266f171509",
    ("ho2018", "light", "lidar", "single"): "12ece3e8dd87083e",
    ("ho2018", "light", "lidar", "vector"): "c1a2303cf1168b9e",
    ("ho2018", "light", "lidar", "group"): "05c3e7cb733f396a",
    ("ho2018", "medium", "default", "single"): "1769b3e47cd31dc1",
    ("ho2018", "medium", "default", "vector"): "12e3bd5aa40c23b6",
    ("ho2018", "medium", "default", "group"): "b707ff12fb0c7a27",
    ("ho2018", "medium", "short", "single"): "d65788dc78b18e21",
    ("ho2018", "medium", "short", "vector"): "6002ee7e181dd9c3",
    ("ho2018", "medium", "short", "group"): "548f5f654f3a92e6",
    ("ho2018", "medium", "table3", "single"): "8c4d8aeea422e76d",
    ("ho2018", "medium", "table3", "vector"): "4f86e5caaa16279f",
    ("ho2018", "medium", "table3", "group"): "b945e16a723cbd3f",
    ("ho2018", "medium", "unchecked", "single"): "8bde4c6386da4a14",
    ("ho2018", "medium", "unchecked", "vector"): "f0c76c5fe5345815",
    ("ho2018", "medium", "unchecked", "group"): "40555e81d5aba1e4",
    ("ho2018", "medium", "lidar", "single"): "52dca672dae04a95",
    ("ho2018", "medium", "lidar", "vector"): "df9d8f7f47a8ab6c",
    ("ho2018", "medium", "lidar", "group"): "389f196b66de07ef",
    ("ho2018", "heavy", "default", "single"): "b24c493ece4dc1bf",
    ("ho2018", "heavy", "default", "vector"): "1021a52d61ce612a",
    ("ho2018", "heavy", "default", "group"): "0a8eae4c40fc2001",
    ("ho2018", "heavy", "short", "single"): "664326f3ef3ff198",
    ("ho2018", "heavy", "short", "vector"): "9b1b66fa47985463",
    ("ho2018", "heavy", "short", "group"): "4ead4c2cd6ecb170",
    ("ho2018", "heavy", "table3", "single"): "3fbca80a2e65ab0d",
    ("ho2018", "heavy", "table3", "vector"): "ebfdb249256f947e",
    ("ho2018", "heavy", "table3", "group"): "ba0bddd336751060",
    ("ho2018", "heavy", "unchecked", "single"): "358f55a1c5ecd554",
    ("ho2018", "heavy", "unchecked", "vector"): "a3625c59ca62cdb7",
    ("ho2018", "heavy", "unchecked", "group"): "81e6e82a4b15e98e",
    ("ho2018", "heavy", "lidar", "single"): "a5385d35a82258cc",
    ("ho2018", "heavy", "lidar", "vector"): "f1522c58311049cd",
    ("ho2018", "heavy", "lidar", "group"): "4e1f6dee6e0d89e9",
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

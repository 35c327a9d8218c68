"""Golden trajectories: the simulator's behaviour, bit for bit, under fixed seeds and actions.

Every preset at every traffic density is stepped in-process as a single environment and as a
vector environment (next-step autoreset), and, for the shared road, as an arena group of the
server with three cars (the path where only the car that ended restarts). Each run feeds a
SHA-256 of everything an agent receives: observations, rewards, both flags and the whole info
(action mask, applied action, reward terms, episode metrics). Variants switch on what the
defaults leave quiet: collisions (no lane-change check, so random weaving crashes), short
episodes (truncation and autoreset), an RGB camera, and a LIDAR-only car.

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
VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "short": SHORT,
    # Without the lane-change check random weaving collides: terminations and their reward.
    "reckless": {**SHORT, "ego.lane_change_check": False},
    "rgb": {"camera.rgb": True, "camera.width_px": 40, "camera.height_px": 30, **SHORT},
    "lidar-only": {"camera.enabled": False, **SHORT},
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

# (preset, density, variant, runner) -> digest, recorded on main at 6041545 before the
# simulator was split into rooms.
GOLDEN: dict[tuple[str, str, str, str], str] = {
    ("min2018", "light", "default", "single"): "e7287e5aa04e31c1",
    ("min2018", "light", "default", "vector"): "b4a8dbfe2876b674",
    ("min2018", "light", "default", "group"): "7ee2a5eca1c0f118",
    ("min2018", "light", "short", "single"): "b28c7a9b6d237fab",
    ("min2018", "light", "short", "vector"): "8441f71537f61171",
    ("min2018", "light", "short", "group"): "608e315ce417bd05",
    ("min2018", "light", "reckless", "single"): "5041002c58ede08b",
    ("min2018", "light", "reckless", "vector"): "b4d24476000986c0",
    ("min2018", "light", "reckless", "group"): "5e4a83a500e3b27a",
    ("min2018", "light", "rgb", "single"): "4b8e79617c4b1f71",
    ("min2018", "light", "rgb", "vector"): "1ef78848dee3d1dc",
    ("min2018", "light", "rgb", "group"): "06d8dacda2275061",
    ("min2018", "light", "lidar-only", "single"): "118787a260bd0bed",
    ("min2018", "light", "lidar-only", "vector"): "88793ccb1da55d4a",
    ("min2018", "light", "lidar-only", "group"): "f592e006ae23c51d",
    ("min2018", "medium", "default", "single"): "ad05ad673cf067e1",
    ("min2018", "medium", "default", "vector"): "cb76fc05d7412558",
    ("min2018", "medium", "default", "group"): "3746802454d60885",
    ("min2018", "medium", "short", "single"): "fe1d4875ed2c6988",
    ("min2018", "medium", "short", "vector"): "dd84f2c83d4f6a71",
    ("min2018", "medium", "short", "group"): "6f7c57553e85b78f",
    ("min2018", "medium", "reckless", "single"): "f8b78a6c6a8113b8",
    ("min2018", "medium", "reckless", "vector"): "675057078371ad0f",
    ("min2018", "medium", "reckless", "group"): "13332417888bf6d4",
    ("min2018", "medium", "rgb", "single"): "1df36ac13eb2d765",
    ("min2018", "medium", "rgb", "vector"): "ef3b817daef49c6e",
    ("min2018", "medium", "rgb", "group"): "9c5a0cb4ed8e22ef",
    ("min2018", "medium", "lidar-only", "single"): "84cb0b60c59b9b16",
    ("min2018", "medium", "lidar-only", "vector"): "0b3c620bbb5b0c6c",
    ("min2018", "medium", "lidar-only", "group"): "741e7d837ac07868",
    ("min2018", "heavy", "default", "single"): "4cb0e72ff937dc70",
    ("min2018", "heavy", "default", "vector"): "a1e683eb629faf4a",
    ("min2018", "heavy", "default", "group"): "d70f6b4729306e94",
    ("min2018", "heavy", "short", "single"): "b8cd88884f0b6715",
    ("min2018", "heavy", "short", "vector"): "6b6e0830c4aa48a8",
    ("min2018", "heavy", "short", "group"): "24d99eb1735ad671",
    ("min2018", "heavy", "reckless", "single"): "e0413553ae4326eb",
    ("min2018", "heavy", "reckless", "vector"): "e908ddacfbb0b38f",
    ("min2018", "heavy", "reckless", "group"): "cc1677cf445e2745",
    ("min2018", "heavy", "rgb", "single"): "5726fcea787cb6ba",
    ("min2018", "heavy", "rgb", "vector"): "49818baf2a4a2c91",
    ("min2018", "heavy", "rgb", "group"): "01b103345e1532fd",
    ("min2018", "heavy", "lidar-only", "single"): "30fa5cf6980b8bfc",
    ("min2018", "heavy", "lidar-only", "vector"): "bbc7ae4f40ea42f0",
    ("min2018", "heavy", "lidar-only", "group"): "50d31d8a095e29a3",
}


def _cases() -> list[tuple[str, str, str, str]]:
    return [
        (preset, density, variant, runner)
        for preset in sorted(PRESETS)
        for density in DENSITIES
        for variant in VARIANTS
        for runner in RUNNERS
    ]


@pytest.mark.parametrize("preset,density,variant,runner", _cases())
def test_trajectory_matches_its_golden_digest(preset, density, variant, runner):
    overrides = {"traffic.density": density, **VARIANTS[variant]}
    digest = RUNNERS[runner](preset, overrides)
    key = (preset, density, variant, runner)
    if os.environ.get("OVERTAKE_GOLDEN_PRINT"):
        print(f"\n    {key!r}: {digest!r},")
    assert key in GOLDEN, f"no golden digest for {key}: record one (OVERTAKE_GOLDEN_PRINT=1)"
    assert digest == GOLDEN[key], (
        f"{key} stepped differently from its golden run: digest {digest}, recorded {GOLDEN[key]}"
    )


def test_the_golden_cases_cover_collisions_and_episode_ends():
    """The variants exercise what they are there for (else a digest guards nothing)."""
    envs = HighwayVectorEnv(
        num_envs=VECTOR_ARENAS, overrides={"traffic.density": "heavy", **VARIANTS["reckless"]}
    )
    rng = np.random.default_rng(12)
    envs.reset(seed=7)
    terminated_total = truncated_total = 0
    for _ in range(VECTOR_STEPS):
        _, _, terminated, truncated, _ = envs.step(rng.integers(ACTION_COUNT, size=VECTOR_ARENAS))
        terminated_total += int(terminated.sum())
        truncated_total += int(truncated.sum())
    assert terminated_total >= 1 and truncated_total >= 1

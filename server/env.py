"""In-process Gymnasium environments over the simulation core.

``HighwayEnv`` is one agent on one arena; ``HighwayVectorEnv`` steps N arenas in one numpy pass
with Gymnasium 1.x's default next-step autoreset: the step after an episode ends resets that
arena (ignoring its action) and returns the first observation of the new episode with reward 0
and terminated = truncated = False.

Info carries, every step: ``action_mask`` (int8, 1 = the action can be taken now),
``action_applied`` (the action actually taken: a masked lateral action becomes keep) and
``reward_terms`` (each term of the reward); at the end of an episode also ``metrics``, the
papers' episode metrics (:data:`overtake.protocol.vocabulary.METRIC_FIELDS`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from overtake.protocol.envs import (
    ReportsEpisodeLength,
    arena_seeds,
    check_actions,
    check_render_mode,
)
from overtake.protocol.messages import BehaviourSpec, WorldFrame
from overtake.protocol.vocabulary import ACTION_COUNT, EPISODE_COUNTS, METRIC_FIELDS

from .sim import HighwaySim, SimConfig, StepResult, autoreset_round, make_config
from .sim.planner import Planner
from .sim.render import render_top_down
from .spec import behaviour_spec
from .world import world_frame

try:  # Gymnasium >= 1.1 names the autoreset modes; 1.0 only has next-step autoreset.
    from gymnasium.vector import AutoresetMode

    _NEXT_STEP: Any = AutoresetMode.NEXT_STEP
except ImportError:  # pragma: no cover - Gymnasium 1.0
    _NEXT_STEP = "NextStep"


def _resolve_config(
    preset: str, overrides: Mapping[str, Any] | None, config: SimConfig | None
) -> SimConfig:
    if config is not None:
        if overrides:
            raise ValueError("pass either a config or a preset with overrides, not both")
        return config
    return make_config(preset, overrides)


def observation_space(sim: HighwaySim) -> spaces.Dict:
    """The Dict observation space of one agent of ``sim``: one Box per sensor."""
    return spaces.Dict(
        {
            key: spaces.Box(low=box.low, high=box.high, shape=box.shape, dtype=box.dtype.type)
            for key, box in sim.observation_spaces().items()
        }
    )


class HighwayEnv(ReportsEpisodeLength, gym.Env):
    """One agent on a simulated highway (Min et al. 2018 by default)."""

    # Gymnasium's convention: a class attribute, replaced per instance with its frame rate.
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        preset: str = "min2018",
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.config = _resolve_config(preset, overrides, config)
        self.render_mode = render_mode
        self.sim = HighwaySim(self.config, num_arenas=1, agents_per_arena=1)
        self.observation_space = observation_space(self.sim)
        self.action_space = spaces.Discrete(ACTION_COUNT)
        self.decision_period_s = self.config.episode.decision_period_s
        self.max_episode_steps = self.config.episode.max_decisions
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.decision_period_s}

    def _observation(self) -> dict[str, np.ndarray]:
        return {key: value[0, 0] for key, value in self.sim.observe().items()}

    def _info(self, result: StepResult | None) -> dict[str, Any]:
        info: dict[str, Any] = {"action_mask": self.sim.action_mask()[0, 0]}
        if result is None:
            info["action_applied"] = -1
            info["reward_terms"] = {name: 0.0 for name in self.sim.reward_terms}
            return info
        info["action_applied"] = int(result.action_applied[0, 0])
        info["reward_terms"] = {name: float(v[0, 0]) for name, v in result.reward_terms.items()}
        if result.terminated[0, 0] or result.truncated[0, 0]:
            info["metrics"] = {name: float(v[0, 0]) for name, v in self.sim.metrics().items()}
        return info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.sim.reset(seeds=[seed])
        return self._observation(), self._info(None)

    def step(self, action):
        result = self.sim.step(check_actions(action, 1, single=True).reshape(1, 1))
        info = self._info(result)
        return (
            self._observation(),
            float(result.reward[0, 0]),
            bool(result.terminated[0, 0]),
            bool(result.truncated[0, 0]),
            info,
        )

    # gymnasium 1.2 (which the rllib extra pins) types render with a TypeVar, 1.4 does not.
    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        if self.render_mode == "rgb_array":
            return render_top_down(self.sim)
        return None

    @property
    def sim_config(self) -> dict[str, Any]:
        """The resolved configuration as plain nested data, a record (as the remote env
        reports it): read :attr:`behaviour_spec` for what an agent sees and drives."""
        return json.loads(json.dumps(dataclasses.asdict(self.config)))

    @property
    def behaviour_spec(self) -> BehaviourSpec:
        """What an agent sees and drives, as a server describes its arenas (protocol 1.5)."""
        return behaviour_spec(self.sim)

    def action_masks(self) -> np.ndarray:
        """The current action mask (the name sb3-contrib's MaskablePPO looks for)."""
        return self.sim.action_mask()[0, 0]

    def planner_action(self) -> int:
        """What the privileged planner (:mod:`overtake.server.sim.planner`), reading the true
        state, would do now: a reference to compare policies with, not one to train."""
        if not hasattr(self, "_planner"):
            self._planner = Planner(self.sim)
        return int(self._planner.act()[0, 0])


class HighwayVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` independent arenas stepped together by one simulation core."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": _NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        preset: str = "min2018",
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.config = _resolve_config(preset, overrides, config)
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.sim = HighwaySim(self.config, num_arenas=num_envs, agents_per_arena=1)
        self.single_observation_space = observation_space(self.sim)
        self.single_action_space = spaces.Discrete(ACTION_COUNT)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, ACTION_COUNT))
        self.decision_period_s = self.config.episode.decision_period_s
        self.max_episode_steps = self.config.episode.max_decisions
        self._autoreset = np.zeros(num_envs, dtype=bool)

    @property
    def sim_config(self) -> dict[str, Any]:
        """The resolved configuration as plain nested data, a record (as the remote env
        reports it): read :attr:`behaviour_spec` for what an agent sees and drives."""
        return json.loads(json.dumps(dataclasses.asdict(self.config)))

    @property
    def behaviour_spec(self) -> BehaviourSpec:
        """What an agent sees and drives, as a server describes its arenas (protocol 1.5)."""
        return behaviour_spec(self.sim)

    def world_frame(
        self,
        index: int,
        observations: dict[str, np.ndarray],
        reward: float,
        action_applied: int,
        reward_terms: dict[str, float],
        trainer_step: int = -1,
    ) -> WorldFrame:
        """Environment ``index``'s road now, as a spectator of a server would see it: its
        trainer's recording draws it in-process (``observations`` its latest, unbatched;
        the reward, action and terms of its last step)."""
        names = self.sim.reward_terms
        return world_frame(
            self.sim,
            index,
            server="in-process",
            group=0,
            arena_id=index,
            round_=int(self.sim.state.decisions[index]),
            observations={name: np.asarray(value)[None] for name, value in observations.items()},
            reward=np.array([reward]),
            action_applied=np.array([action_applied]),
            reward_terms=np.array([[reward_terms.get(name, 0.0) for name in names]]),
            trainer_step=trainer_step,
        )

    def _observations(self) -> dict[str, np.ndarray]:
        return {key: value[:, 0] for key, value in self.sim.observe().items()}

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ):
        seeds = arena_seeds(seed, self.num_envs)
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(seeds[0])
        self.sim.reset(seeds=seeds)
        self._autoreset[:] = False
        n = self.num_envs
        info = {
            "action_mask": self.sim.action_mask()[:, 0],
            "action_applied": np.full(n, -1, dtype=np.int64),
            "reward_terms": {name: np.zeros(n) for name in self.sim.reward_terms},
            "episode_counts": self._episode_counts(),
        }
        return self._observations(), info

    def _episode_counts(self) -> dict[str, np.ndarray]:
        """Each environment's collisions and emergency brakes in its episode so far (copies:
        the state moves on); a decision whose count rose had one."""
        state = self.sim.state
        return {name: getattr(state, name)[:, 0].copy() for name in EPISODE_COUNTS}

    def step(self, actions):
        actions = check_actions(actions, self.num_envs, single=False)
        result = autoreset_round(self.sim, actions[:, None], self._autoreset[:, None])
        info: dict[str, Any] = {
            "action_mask": self.sim.action_mask()[:, 0],
            "action_applied": result.action_applied[:, 0],
            "reward_terms": {name: value[:, 0] for name, value in result.reward_terms.items()},
            "episode_counts": self._episode_counts(),
        }
        ended = result.ended[:, 0]
        if ended.any():
            metrics = self.sim.metrics()
            info["metrics"] = {
                name: np.where(ended, metrics[name][:, 0], 0.0) for name in METRIC_FIELDS
            }
            info["_metrics"] = ended
        self._autoreset = ended
        return (
            self._observations(),
            result.reward[:, 0],
            result.terminated[:, 0],
            result.truncated[:, 0],
            info,
        )

    def planner_actions(self) -> np.ndarray:
        """(num_envs,) what the privileged planner (:mod:`overtake.server.sim.planner`),
        reading the true state, would do now in each arena."""
        if not hasattr(self, "_planner"):
            self._planner = Planner(self.sim)
        return self._planner.act()[:, 0]

    def render(self) -> tuple[np.ndarray, ...] | None:  # type: ignore[override, unused-ignore]
        if self.render_mode == "rgb_array":
            return tuple(render_top_down(self.sim, arena=i) for i in range(self.num_envs))
        return None

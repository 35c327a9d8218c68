"""In-process Gymnasium environments: overtake's faces over the simulator in this process.

``HighwayEnv`` is one agent on one arena; ``HighwayVectorEnv`` steps N arenas in one numpy pass
with Gymnasium 1.x's default next-step autoreset: the step after an episode ends resets that
arena (ignoring its action) and returns the first observation of the new episode with reward 0
and terminated = truncated = False. Both are :mod:`overtake.envs.faces` over a
:class:`~overtake.server.engine.local.LocalEngine`, the server's own arena group, and so equal the
remote environments bit for bit.

Info carries, every step: ``action_mask`` (int8, 1 = the action can be taken now),
``action_applied`` (the action actually taken: a masked lateral action becomes keep; under
``ego.applied_as_driven``, ho2018's, what his safety rule made of it), ``reward_terms``
(each term of the reward) and ``episode_counts`` (the episode's collisions and emergency
brakes so far); at the end of an episode also ``metrics``, the papers' episode
metrics (:data:`overtake.protocol.vocabulary.METRIC_FIELDS`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from overtake.envs.faces import SingleFace, VectorFace
from overtake.protocol.errors import BadConfig
from overtake.protocol.messages import Translation
from overtake.protocol.vocabulary import DEFAULT_PRESET

from ..sim import HighwaySim, SimConfig, settings_history
from .local import LocalEngine, LocalRoad, local_simulator
from .requested import translated


def in_process_config(
    preset: str,
    overrides: Mapping[str, Any] | None,
    config: SimConfig | None,
    as_recorded: Mapping[str, Any] | None = None,
    observations: Sequence[str] = (),
    ego_fields: Sequence[str] = (),
    translation: Translation | None = None,
) -> SimConfig:
    """``config``, or the preset with its overrides (not both) over ``translation``'s
    settings (a configuration in another simulator's words, translated as a server
    translates it), or with ``as_recorded`` (a record's configuration) the simulator that
    record was made on; its ego vector holding ``ego_fields`` and only the sensors of
    ``observations`` on where they name some
    (:func:`~.sim.settings_history.requested_config`)."""
    if config is not None and not isinstance(config, SimConfig):
        hint = (
            ": highway-env's keys go to gym.make('overtake/highway-fast-v0', config={...}), "
            "overtake's settings to overrides={'road.lane_count': 4, ...}"
            if isinstance(config, Mapping)
            else ""
        )
        raise BadConfig(
            f"config= takes a SimConfig (overtake.server.sim.make_config), got a "
            f"{type(config).__name__}{hint}"
        )
    if config is None:
        return settings_history.requested_config(
            preset,
            overrides or {},
            as_recorded,
            observations,
            ego_fields,
            translated(preset, translation),
        )
    if overrides or as_recorded or translation is not None:
        raise ValueError("pass either a config or a preset with overrides, not both")
    return config.reading_ego_fields(tuple(ego_fields)).observing(tuple(observations))


class _InProcess:
    """What an in-process face offers besides its face: the simulation itself."""

    config: SimConfig

    @property
    def sim(self) -> HighwaySim:
        """The simulation core (tests and benchmarks read its state)."""
        (engine,) = self.simulator.parts  # type: ignore[attr-defined]
        assert isinstance(engine, LocalEngine)
        return engine.sim

    @property
    def road(self) -> LocalRoad:
        road = self.simulator.road  # type: ignore[attr-defined]
        assert isinstance(road, LocalRoad)
        return road


class HighwayEnv(_InProcess, SingleFace):
    """One agent on a simulated highway (Min et al. 2018 by default)."""

    def __init__(
        self,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
        as_recorded: Mapping[str, Any] | None = None,
        observations: Sequence[str] = (),
        ego_fields: Sequence[str] = (),
        translation: Translation | None = None,
    ) -> None:
        self.config = in_process_config(
            preset, overrides, config, as_recorded, observations, ego_fields, translation
        )
        super().__init__(local_simulator(self.config, arenas=1), render_mode)

    def planner_action(self) -> int:
        """What the privileged planner (:mod:`overtake.server.sim.planner`), reading the true
        state, would do now: a reference to compare policies with, not one to train."""
        return int(self.road.planner_actions()[0])


class HighwayVectorEnv(_InProcess, VectorFace):
    """``num_envs`` independent arenas stepped together by one simulation core."""

    def __init__(
        self,
        num_envs: int = 1,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
        as_recorded: Mapping[str, Any] | None = None,
        observations: Sequence[str] = (),
        ego_fields: Sequence[str] = (),
        translation: Translation | None = None,
    ) -> None:
        self.config = in_process_config(
            preset, overrides, config, as_recorded, observations, ego_fields, translation
        )
        super().__init__(local_simulator(self.config, arenas=num_envs), num_envs, render_mode)

    def planner_actions(self) -> np.ndarray:
        """(num_envs,) what the privileged planner (:mod:`overtake.server.sim.planner`),
        reading the true state, would do now in each arena."""
        return self.road.planner_actions()

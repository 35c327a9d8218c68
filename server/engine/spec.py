"""The behaviour spec: the one description a consumer reads of what an agent sees and drives.

Built here once, from the simulation, for the server's groups (sent with every Opened) and the
in-process environments alike, so that both describe an arena the same way: the spaces, the
road, the car, and each observation's named columns and reach (protocol 1.5) and how its
normalised columns were scaled (protocol 1.11). The full
configuration travels with it as a record (``config_json``); nothing reads it as an interface.
"""

from __future__ import annotations

import dataclasses
import json

from overtake.protocol.messages import (
    BehaviourSpec,
    CarSpec,
    ColumnScale,
    ObservationSpec,
    Reach,
    RoadSpec,
)
from overtake.protocol.vocabulary import ACTION_COUNT

from ..sim import HighwaySim
from ..sim.sensors import SensorFacts


def _reach(facts: SensorFacts) -> Reach | None:
    if not facts.sees:
        return None
    return Reach(
        ahead_m=facts.ahead_m, behind_m=facts.behind_m, side_m=facts.side_m, range_m=facts.range_m
    )


def behaviour_spec(sim: HighwaySim) -> BehaviourSpec:
    """What a client needs to rebuild exactly the in-process spaces and to read them."""
    config = sim.config
    facts = sim.observation_facts()
    # In the order of the in-process Dict space, which Gymnasium sorts by name.
    observations = tuple(
        ObservationSpec(
            name=name,
            shape=box.shape,
            dtype=box.dtype.name,
            low=box.low,
            high=box.high,
            columns=facts[name].columns,
            reach=_reach(facts[name]),
            scales=tuple(
                ColumnScale(column=column, low=low, high=high)
                for column, low, high in facts[name].scales
            ),
        )
        for name, box in sorted(sim.observation_spaces().items())
    )
    return BehaviourSpec(
        name=f"Highway?preset={config.preset}",
        preset=config.preset,
        observations=observations,
        action_branches=(ACTION_COUNT,),
        action_names=tuple(sim.actions.names),  # highway-env's names in its scenes
        reward_terms=sim.reward_terms,
        metric_fields=sim.metric_fields,
        decision_period_s=config.episode.decision_period_s,
        max_episode_steps=config.episode.max_decisions,
        agents_per_arena=sim.agents,
        config_json=json.dumps(dataclasses.asdict(config)),
        road=RoadSpec(lane_count=config.road.lane_count, lane_width_m=config.road.lane_width_m),
        car=CarSpec(
            length_m=config.ego.length_m,
            width_m=config.ego.width_m,
            min_speed_kmh=config.ego.cruise_min_kmh,
            max_speed_kmh=config.ego.cruise_max_kmh,
        ),
    )

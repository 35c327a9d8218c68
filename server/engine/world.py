"""An arena as spectators and recordings see it: a :class:`WorldFrame` of the simulator's
snapshot of its road, with its agents' latest observations and rewards. The server's groups
send them to spectators; an in-process environment gives them to its trainer's recording."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.messages import WorldFrame
from overtake.protocol.vocabulary import AGENT_KIND

from ..sim import HighwaySim

if TYPE_CHECKING:
    from ..service.groups import Group
    from .rounds import Rounds


def world_frame(
    sim: HighwaySim,
    arena: int,
    *,
    server: str,
    group: int,
    arena_id: int,
    round_: int,
    observations: dict[str, np.ndarray],
    reward: np.ndarray,
    action_applied: np.ndarray,
    reward_terms: np.ndarray,
    trainer_step: int = -1,
) -> WorldFrame:
    """Arena ``arena`` of ``sim`` (``arena_id`` to the world); the per-agent arrays are its
    agents' latest: observations (N, ...) by name, reward (N,), the action applied (N,) and
    the reward terms (N, terms)."""
    world = sim.world_snapshot(arena)
    return WorldFrame(
        server=server,
        group=group,
        arena=arena_id,
        round=round_,
        sim_time_s=world.sim_time_s,
        lane_count=world.lane_count,
        lane_width_m=world.lane_width_m,
        agent_kind=AGENT_KIND,
        agent_active=world.agent_active,
        x_m=world.x_m,
        y_m=world.y_m,
        speed_mps=world.speed_mps,
        kind=world.kind,
        active=world.active,
        observations=observations,
        # Copies: the frame may be encoded or recorded after the caller's arrays move on.
        reward=np.array(reward, dtype=np.float64),
        action_applied=np.array(action_applied, dtype=np.int64),
        reward_terms=np.array(reward_terms, dtype=np.float64),
        reward_term_names=sim.reward_terms,
        trainer_step=trainer_step,
        half_length_m=world.half_length_m,
        half_width_m=world.half_width_m,
        agent_heading_rad=world.agent_heading_rad,
    )


def group_world_frame(group: Group, arena: int, observations: dict[str, np.ndarray]) -> WorldFrame:
    """Arena ``arena`` (an index in ``group``) as spectators and recordings see it: the
    simulator's snapshot of its road, with the agents' latest observations and rewards."""
    return rounds_world_frame(
        group.rounds,
        arena,
        observations,
        server=group.server,
        group=group.group_id,
        arena_id=group.arena_ids[arena],
        trainer_step=group.trainer_step,
    )


def rounds_world_frame(
    rounds: Rounds,
    arena: int,
    observations: dict[str, np.ndarray],
    *,
    server: str,
    group: int,
    arena_id: int,
    trainer_step: int,
) -> WorldFrame:
    """:func:`group_world_frame` of any :class:`~.rounds.Rounds` (an in-process engine's
    too), named as given."""
    return world_frame(
        rounds.sim,
        arena,
        server=server,
        group=group,
        arena_id=arena_id,
        round_=rounds.round,
        observations={name: value[arena] for name, value in observations.items()},
        reward=rounds.last_reward[arena],
        action_applied=rounds.last_applied[arena],
        reward_terms=rounds.last_terms[arena],
        trainer_step=trainer_step,
    )

"""Rounds with Gymnasium's next-step autoreset: the one place an ended episode restarts.

The in-process vector environment and the server's arena groups both step through
:func:`autoreset_round`. An agent whose episode ended in the previous round restarts in this
one: its action is ignored and its row has reward 0, both flags false and the first
observation of its new episode (Gymnasium 1.x's next-step autoreset). With one agent per arena
the arena is reset whole, continuing its generator's stream, so that a remote arena reproduces
an in-process one bit for bit. With several agents on a road only the cars that ended restart:
they are taken off the road for the round and placed back behind the others after it, while
the road goes on for everyone else.
"""

from __future__ import annotations

import numpy as np

from .core import HighwaySim, StepResult


def autoreset_round(
    sim: HighwaySim, actions: np.ndarray, restarting: np.ndarray, present: np.ndarray | None = None
) -> StepResult:
    """Step every arena of ``sim`` one round with (A, N) ``actions``; slots that restarted or
    have no car on the road get reward 0, no flags and action -1.

    ``restarting`` (A, N): the agents whose episode ended last round; they restart now.
    ``present`` (A, N): the agents whose car is on the road (None: all of them); the others'
    rows are zero.
    """
    arenas, n = sim.num_arenas, sim.agents
    on_road = np.ones((arenas, n), dtype=bool) if present is None else present
    if not restarting.any() and on_road.all():
        # The common round: every car on the road, nobody restarting.
        return sim.step(actions)
    reward = np.zeros((arenas, n))
    terminated = np.zeros((arenas, n), dtype=bool)
    truncated = np.zeros((arenas, n), dtype=bool)
    applied = np.full((arenas, n), -1, dtype=np.int64)
    terms = {name: np.zeros((arenas, n)) for name in sim.reward_terms}
    respawn: list[tuple[int, np.ndarray]] = []
    if n == 1:
        # One agent per arena: the arena restarts whole, exactly as in-process.
        resetting = np.flatnonzero(restarting[:, 0])
        if resetting.size:
            sim.reset(resetting)
        stepping = np.flatnonzero(~restarting[:, 0])
    else:
        for arena in np.flatnonzero(restarting.any(axis=1)):
            slots = np.flatnonzero(restarting[arena])
            sim.remove_agents(int(arena), slots)
            respawn.append((int(arena), slots))
        stepping = np.arange(arenas)
    if stepping.size:
        result = sim.step(actions[stepping], arenas=None if stepping.size == arenas else stepping)
        live = on_road[stepping] & ~restarting[stepping]
        reward[stepping] = np.where(live, result.reward, 0.0)
        terminated[stepping] = result.terminated & live
        truncated[stepping] = result.truncated & live
        applied[stepping] = np.where(live, result.action_applied, -1)
        for name, value in result.reward_terms.items():
            terms[name][stepping] = np.where(live, value, 0.0)
    for row, slots in respawn:
        sim.respawn_agents(row, slots)
    return StepResult(
        reward=reward,
        reward_terms=terms,
        terminated=terminated,
        truncated=truncated,
        action_applied=applied,
    )

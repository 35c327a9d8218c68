"""The random numbers of one decision: one fixed-size block of uniforms per arena.

Each arena owns one ``np.random.Generator``. Every random number an arena uses while stepping
is drawn from it in one block per decision, ``UNIFORMS_PER_VEHICLE`` uniforms for each vehicle
slot whether it needs them or not, and each column has one meaning (below). So an arena's
episode depends only on its seed and its actions, bit for bit, whatever other arenas share the
batch and whatever happens on its road.
"""

from __future__ import annotations

import numpy as np

# Positions tried per traffic (re)spawn: the first half in the spawn window of its side, the
# rest anywhere in the kept range on that side (when the window is full).
SPAWN_CANDIDATES = 10
# Columns of a vehicle's row: side, anchor agent, candidate lanes and offsets, behaviour,
# desired speed, speed-change event and value, random lane-change event.
U_SIDE, U_ANCHOR = 0, 1
U_LANE = 2
U_OFFSET = U_LANE + SPAWN_CANDIDATES
U_BEHAVIOUR = U_OFFSET + SPAWN_CANDIDATES
U_SPEED, U_CHANGE, U_NEW_SPEED = U_BEHAVIOUR + 1, U_BEHAVIOUR + 2, U_BEHAVIOUR + 3
U_RANDOM_LANE = U_NEW_SPEED + 1
UNIFORMS_PER_VEHICLE = U_RANDOM_LANE + 1
# Min et al.'s spawners (traffic.entry = "spawners") try one spot at a time, from the row of
# their first slot: a try's wait until the next takes the second candidate lane's column.
U_SPAWNER_WAIT = U_LANE + 1


def draw_uniforms(rngs: list[np.random.Generator], rows: np.ndarray, vehicles: int) -> np.ndarray:
    """(len(rows), vehicles, UNIFORMS_PER_VEHICLE) uniforms, each arena's from its generator."""
    uniforms = np.empty((rows.size, vehicles, UNIFORMS_PER_VEHICLE))
    for i, row in enumerate(rows):
        rngs[row].random(out=uniforms[i])
    return uniforms

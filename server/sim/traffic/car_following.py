"""Car-following: the Intelligent Driver Model (Treiber et al.), and whom each car follows.

Traffic follows its leader with an IDM of its behaviour's parameters; the agents' cruise
control (:mod:`..assist`) keeps the IDM's distance-keeping term and replaces its free-road term
with a speed controller towards the cruise target. The physics frame does this in one compiled
loop (:func:`.kernels.follow_and_accelerate`), MOBIL the accelerations a lane change would
bring in another (:func:`.kernels.mobil_decide`, with :func:`.kernels.idm`);
:func:`idm_desired_gap` here is the spawner's, for the room a new car needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def idm_desired_gap(
    speed: np.ndarray,
    closing_speed: np.ndarray,
    time_headway: np.ndarray,
    min_gap: np.ndarray,
    two_sqrt_ab: np.ndarray,
) -> np.ndarray:
    """The IDM's desired bumper-to-bumper gap s* (m)."""
    return min_gap + np.maximum(0.0, speed * time_headway + speed * closing_speed / two_sqrt_ab)


# Built every frame: a plain record (a frozen one pays a setattr call per field).
@dataclass(slots=True)
class Following:
    """Whom each vehicle follows this frame, (A, V) each: the nearer of the leaders in its
    lane and, while it changes lanes, in its target lane."""

    gap_m: np.ndarray  # bumper to bumper; NO_GAP_M where nobody is ahead
    leader: np.ndarray  # flat index (arena * V + column) of the leader
    has_leader: np.ndarray  # bool
    leader_speed_mps: np.ndarray  # own speed where there is no leader
    closing_mps: np.ndarray  # own speed minus the leader's

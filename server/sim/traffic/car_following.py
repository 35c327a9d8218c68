"""Car-following: the Intelligent Driver Model (Treiber et al.), and whom each car follows.

Traffic follows its leader with an IDM of its behaviour's parameters; the agents' cruise
control (:mod:`..assist`) keeps the IDM's distance-keeping term and replaces its free-road term
with a speed controller towards the cruise target. The physics frame does this in one compiled
loop (:func:`..kernels.follow_and_accelerate`); :func:`idm_accel` here, vectorised over
(arenas, vehicles), is MOBIL's, for the accelerations a lane change would bring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def idm_accel(
    speed: np.ndarray,
    desired_speed: np.ndarray,
    gap: np.ndarray,
    closing_speed: np.ndarray,
    time_headway: np.ndarray,
    min_gap: np.ndarray,
    max_accel: np.ndarray,
    two_sqrt_ab: np.ndarray,
) -> np.ndarray:
    """Intelligent Driver Model acceleration (m/s^2); arguments broadcast against each other.

    ``closing_speed`` is own speed minus the leader's; ``gap`` is bumper to bumper (m);
    ``two_sqrt_ab`` is 2 * sqrt(max_accel * comfortable_decel), precomputed per vehicle.
    """
    desired_gap = idm_desired_gap(speed, closing_speed, time_headway, min_gap, two_sqrt_ab)
    ratio = speed / desired_speed
    ratio *= ratio
    interaction = desired_gap / np.maximum(gap, 0.1)
    return max_accel * (1.0 - ratio * ratio - interaction * interaction)


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

"""What a round gives the faces, and what their ``info`` says of it.

:class:`StepRows` is what every face reads of a round, one row per agent: the contract's
:class:`~overtake.protocol.rows.Rows`, a :class:`~overtake.protocol.messages.Steps` a server
sends or an in-process engine's own rows (no message); :func:`joined` (the contract's) puts the
rows of a vector environment's parts together. :class:`StepInfo` is the ``info`` the faces hand out,
built from the rows, its fields the vocabulary's :data:`~.vocabulary.INFO_KEYS`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.rows import Rows, joined
from overtake.protocol.vocabulary import EPISODE_COUNTS, INFO_KEYS, WATCH_METRICS

# What the faces read of a round, one row per agent: :class:`Steps` from a server, or an
# in-process engine's own rows (no message); both are the contract's rows.
StepRows = Rows


@dataclass(frozen=True)
class StepInfo:
    """What a step's ``info`` says, read from its Steps; the faces hand it out as a dict
    (:meth:`vector`, :meth:`agent`) whose keys are these fields' names
    (:data:`~overtake.protocol.vocabulary.INFO_KEYS`)."""

    action_mask: np.ndarray
    """(k, ACTION_COUNT) int8, 1 = the action can be taken now"""
    action_applied: np.ndarray
    """(k,) the action actually taken (a masked lateral action becomes keep; -1 at a reset)"""
    reward_terms: dict[str, np.ndarray]
    """each term of the reward, (k,) each"""
    episode_counts: dict[str, np.ndarray]
    """(k,) int64 each: the episode's collisions and emergency brakes so far (and, where driver
    assistance watches lane changes through, the changes it turned back); a decision whose
    count rose had one"""
    metrics: dict[str, np.ndarray]
    """the papers' episode metrics, (k,) each: read where the episode ended"""
    late: np.ndarray
    """(k,) bool: no action came for the car this round (the trainer missed the server's
    deadline, or left the car out of its actions); keep was applied instead"""
    server_restarted: bool
    """the server was lost in this step: the episodes under way were truncated"""
    ended: np.ndarray
    """(k,) bool: whose episode ended here (where :attr:`metrics` hold)"""
    rows: StepRows = dataclasses.field(repr=False)
    """the rows this info was read from (:meth:`agent` reads one of them as :meth:`agent_of`)"""
    spec: BehaviourSpec = dataclasses.field(repr=False)

    @classmethod
    def of(cls, steps: StepRows, spec: BehaviourSpec, *, restarted: bool = False) -> StepInfo:
        fields = spec.metric_fields
        return cls(
            action_mask=steps.action_mask,
            action_applied=steps.action_applied,
            reward_terms={
                name: steps.reward_terms[:, i] for i, name in enumerate(spec.reward_terms)
            },
            # The Steps' metrics are each episode's so far; the counts of events are integers.
            episode_counts={
                name: steps.metrics[:, fields.index(name)].astype(np.int64)
                for name in (*EPISODE_COUNTS, *WATCH_METRICS)
                if name in fields
            },
            metrics={name: steps.metrics[:, i] for i, name in enumerate(fields)},
            late=steps.late,
            server_restarted=restarted,
            ended=steps.ended,
            rows=steps,
            spec=spec,
        )

    @staticmethod
    def agent_of(
        steps: StepRows, spec: BehaviourSpec, row: int, *, restarted: bool = False
    ) -> dict[str, Any]:
        """One agent's info, read straight from row ``row`` (a single environment's every step
        builds no vector's dicts): scalars; ``metrics`` when its episode ended, ``late`` and
        ``server_restarted`` only when true."""
        fields = spec.metric_fields
        metrics = steps.metrics[row]
        terms = steps.reward_terms[row]
        info: dict[str, Any] = {
            "action_mask": steps.action_mask[row],
            "action_applied": int(steps.action_applied[row]),
            "reward_terms": {name: float(terms[i]) for i, name in enumerate(spec.reward_terms)},
            "episode_counts": {
                name: int(metrics[fields.index(name)])
                for name in (*EPISODE_COUNTS, *WATCH_METRICS)
                if name in fields
            },
        }
        if steps.terminated[row] or steps.truncated[row]:
            info["metrics"] = {name: float(metrics[i]) for i, name in enumerate(fields)}
        if steps.late[row]:
            info["late"] = True
        if restarted:
            info["server_restarted"] = True
        return info

    def vector(self) -> dict[str, Any]:
        """A vector environment's info: arrays over its environments; ``metrics`` (0 where no
        episode ended, ``_metrics`` marking where one did), ``late`` and ``server_restarted``
        only when something happened."""
        info: dict[str, Any] = {
            "action_mask": self.action_mask,
            "action_applied": self.action_applied,
            "reward_terms": self.reward_terms,
            "episode_counts": self.episode_counts,
        }
        if self.ended.any():
            info["metrics"] = {
                name: np.where(self.ended, value, 0.0) for name, value in self.metrics.items()
            }
            info["_metrics"] = self.ended
        if self.late.any():
            info["late"] = self.late
        if self.server_restarted:
            info["server_restarted"] = np.ones(self.ended.shape, dtype=bool)
        return info

    def agent(self, row: int) -> dict[str, Any]:
        """One agent's info (row ``row`` of the Steps): scalars; ``metrics`` when its episode
        ended, ``late`` and ``server_restarted`` only when true (:meth:`agent_of`, the one
        place an agent's info is made)."""
        return self.agent_of(self.rows, self.spec, row, restarted=self.server_restarted)


assert tuple(f.name for f in dataclasses.fields(StepInfo))[: len(INFO_KEYS)] == INFO_KEYS


__all__ = ["StepInfo", "StepRows", "joined"]

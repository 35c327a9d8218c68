"""The sensor interface: what every sensor of the simulation offers, and what it looks at.

A sensor has a ``key`` (its observation's name), a :class:`SensorSpace` (the box one agent's
observation lies in) and ``observe(scene)``, which returns every agent's observation at once,
(arenas, agents, *shape). Its configuration section (a :class:`SensorConfig`) says whether it
is on and builds it. The :class:`Scene` is computed once per observation and shared by all
sensors: what each observer sees is worked out only if some sensor asks for it.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from ..physics import headings

if TYPE_CHECKING:
    from ..ahead import CarsAhead
    from ..assist import DriverWarnings
    from ..config import SimConfig
    from ..road import Road
    from ..state import SimState
    from ..vehicles import VehicleKinds


@dataclass(frozen=True, eq=False)
class SensorSpace:
    """One agent's observation: a box of ``shape`` and ``dtype`` within [low, high]."""

    shape: tuple[int, ...]
    dtype: np.dtype
    low: np.ndarray  # of shape and dtype
    high: np.ndarray

    @classmethod
    def uniform(cls, shape: tuple[int, ...], dtype: Any, low: float, high: float) -> SensorSpace:
        """A box with the same bounds everywhere."""
        dtype = np.dtype(dtype)
        return cls(
            shape, dtype, np.full(shape, low, dtype=dtype), np.full(shape, high, dtype=dtype)
        )


@dataclass(frozen=True)
class SensorFacts:
    """What a reader of a sensor's observation needs beyond its box: the names of the last
    axis' entries where they are named (``columns``), and how far it sees, in metres from the
    car's centre along the road, across it and along its rays (0 where that does not apply).
    The behaviour spec carries them (protocol 1.5), and the normalised columns' ranges
    (``scales``: a column's name, the quantity shown as -1 and as 1; protocol 1.11)."""

    columns: tuple[str, ...] = ()
    ahead_m: float = 0.0
    behind_m: float = 0.0
    side_m: float = 0.0
    range_m: float = 0.0
    scales: tuple[tuple[str, float, float], ...] = ()

    @property
    def sees(self) -> bool:
        """Whether it sees any of the road (the action stack does not)."""
        return any((self.ahead_m, self.behind_m, self.side_m, self.range_m))


# Built every observation: a plain record (a frozen one pays a setattr call per field).
@dataclass(slots=True)
class ObserverViews:
    """Per observer (arena-major, agent-minor; O = arenas * agents): where it is and the
    vehicles it can see, (O,) and (O, V). x is relative to each arena's first agent."""

    origin_x: np.ndarray
    origin_y: np.ndarray
    heading: np.ndarray
    car_x: np.ndarray
    car_y: np.ndarray
    car_half_length: np.ndarray
    car_half_width: np.ndarray
    car_visible: np.ndarray  # False for itself, inactive slots and cars off the road


class Scene:
    """What the sensors of one observation look at: the state, the road and vehicle kinds,
    and, each worked out on first use, the observers' views, the cars ahead of the agents and
    the driver-assistance warnings."""

    def __init__(
        self,
        state: SimState,
        kinds: VehicleKinds,
        road: Road,
        agents: int,
        driver_warnings: DriverWarnings,
        warnings: np.ndarray | None = None,
        vehicle_headings: Callable[[], np.ndarray] | None = None,
    ) -> None:
        self.state = state
        self.kinds = kinds
        self.road = road
        self.agents = agents
        self.arenas = state.x_m.shape[0]
        self._driver_warnings = driver_warnings
        self._views: ObserverViews | None = None
        self._ahead: CarsAhead | None = None
        # Given where the simulation already keeps them in its state.
        self._warnings: np.ndarray | None = warnings
        self._vehicle_headings = vehicle_headings
        self._headings: np.ndarray | None = None

    @property
    def headings(self) -> np.ndarray:
        """(A, V) every car's heading, radians from the road's direction, left positive."""
        if self._headings is None:
            self._headings = (
                self._vehicle_headings()
                if self._vehicle_headings is not None
                else headings(
                    self.state, self.kinds, self.road.lane_width_m, self.state.x_m.shape[1]
                )
            )
        return self._headings

    @property
    def views(self) -> ObserverViews:
        if self._views is None:
            self._views = self._observer_views()
        return self._views

    @property
    def ahead(self) -> CarsAhead:
        """Each agent's car ahead."""
        if self._ahead is None:
            self._ahead = self._driver_warnings.cars_ahead(self.state)
        return self._ahead

    @property
    def warnings(self) -> np.ndarray:
        """(A, N, 3) bool: each agent's left, right and forward warnings."""
        if self._warnings is None:
            self._warnings = self._driver_warnings.compute(self.state, self.ahead)
        return self._warnings

    def _observer_views(self) -> ObserverViews:
        st, n, arenas = self.state, self.agents, self.arenas
        x_rel = st.x_m - st.x_m[:, :1]
        kind = np.repeat(st.kind, n, axis=0)
        visible = np.repeat(st.active, n, axis=0)
        visible[np.arange(arenas * n), np.tile(np.arange(n), arenas)] = False
        return ObserverViews(
            origin_x=x_rel[:, :n].reshape(-1),
            origin_y=st.y_m[:, :n].reshape(-1),
            heading=self.headings[:, :n].reshape(-1),
            car_x=np.repeat(x_rel, n, axis=0),
            car_y=np.repeat(st.y_m, n, axis=0),
            car_half_length=self.kinds.half_length[kind],
            car_half_width=self.kinds.half_width[kind],
            car_visible=visible,
        )


class Sensor(Protocol):
    """One observation of every agent."""

    key: str

    def space(self) -> SensorSpace:
        """The box one agent's observation lies in."""
        ...

    def facts(self) -> SensorFacts:
        """Its columns' names and its reach (:class:`SensorFacts`)."""
        ...

    def observe(self, scene: Scene) -> np.ndarray:
        """Every agent's observation, (arenas, agents, *space.shape) of space.dtype."""
        ...


class SensorConfig(abc.ABC):
    """A sensor's configuration section: whether it is on, and how to build it.

    Every section of :class:`~overtake.server.sim.config.SimConfig` that is a SensorConfig is
    a sensor of the simulation; the observation holds the enabled ones, in the order of
    SimConfig's fields.
    """

    enabled: bool
    OBSERVATION: ClassVar[str]
    """the observation's name (its key in the observation dict: ``Sensor.key``)"""

    @abc.abstractmethod
    def build(self, config: SimConfig) -> Sensor:
        """The sensor, for a simulation of ``config``."""

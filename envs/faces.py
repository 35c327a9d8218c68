"""overtake's Gymnasium environments, written once over an engine.

An :class:`Engine` is a group of arenas that answers actions with a round's rows
(:class:`StepRows`): the simulator in this process (:mod:`overtake.server.engine.local`, the rounds
a server's groups play, read straight from the simulator's arrays) or arenas on a server
(:class:`overtake.client.wire.remote.ArenaGroup`, whose rows are the :class:`Steps` messages).
A :class:`Simulator` is what an environment is opened on: its engines (one, or one per part of
a vector environment), the behaviour spec, and what only some simulators have, each a typed
property that is None where it is absent: the :class:`Road` of an in-process simulator (world
frames, pictures, the privileged planner) and the :class:`Network` of a remote one (the
trainer's name, where the arenas are, how often their server was lost).

The faces, :class:`SingleFace` (Gymnasium's ``Env``), :class:`VectorFace` (``VectorEnv``,
next-step autoreset, optionally in parts) and, in :mod:`.parallel_face`, PettingZoo's
``ParallelEnv``, read only those rows; their ``info`` is built in
:class:`~.step_rows.StepInfo`, whose fields are :data:`~overtake.protocol.vocabulary.INFO_KEYS`.
An in-process environment and a remote one are the same face over a different engine, and so
the same bit for bit.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from overtake.protocol.messages import BehaviourSpec, WorldFrame
from overtake.protocol.vocabulary import ACTION_COUNT

from .registry import ReportsEpisodeLength, arena_seeds, check_actions, check_render_mode
from .step_rows import StepInfo, StepRows, joined

try:  # Gymnasium >= 1.1 names the autoreset modes; 1.0 only has next-step autoreset.
    from gymnasium.vector import AutoresetMode

    NEXT_STEP: Any = AutoresetMode.NEXT_STEP
except ImportError:  # pragma: no cover - Gymnasium 1.0
    NEXT_STEP = "NextStep"


class Engine(Protocol):
    """A group of arenas stepped together, answering actions with a round's :class:`StepRows`.

    ``agents`` are this engine's agent ids, its rows. ``restarts`` counts the
    times its server was lost and its arenas reopened (each loss truncates the episodes under
    way). ``trainer_step``, sent with the following actions, is the trainer's step count that
    the road's world frames repeat (-1: none)."""

    restarts: int
    trainer_step: int

    @property
    def agents(self) -> np.ndarray: ...

    def reset(self, arenas: tuple[int, ...], seeds: tuple[int | None, ...]) -> StepRows: ...

    def send(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> None:
        """Actions for this round go out; :meth:`receive` takes the round's Steps."""

    def receive(self) -> StepRows: ...

    def close(self) -> None: ...


@runtime_checkable
class Restorable(Protocol):
    """An engine that keeps its arenas' whole state as plain data and puts it back (another
    configuration or size refused, nothing changed): then it plays on bit for bit as before."""

    restorable: bool  # whether it can now (remote: a 1.8 server, arenas opened alone)

    def snapshot(self) -> dict[str, Any]: ...

    def restore(self, snapshot: Mapping[str, Any]) -> None: ...


@dataclass(frozen=True)
class PictureView:
    """How a top-down picture is framed, as highway-env's viewer frames its road
    (``screen_width``, ``screen_height``, ``scaling``, ``centering_position``): its size in
    pixels, its scale, and where the watched car sits (fractions of the width and height)."""

    width_px: int = 600
    height_px: int = 150
    pixels_per_m: float = 5.5
    centering: tuple[float, float] = (0.3, 0.5)


class Road(Protocol):
    """What an in-process simulator shows of its road, which a remote one keeps to itself (its
    roads reach a recording through a spectator)."""

    def world_frame(self, arena: int) -> WorldFrame:
        """Arena ``arena`` now, as a spectator of a server would see it (the observations,
        reward, action and terms of its last round)."""

    def picture(self, arena: int, view: PictureView | None = None) -> np.ndarray:
        """Arena ``arena`` drawn from above, an RGB array (framed by ``view`` where given)."""

    def planner_actions(self) -> np.ndarray:
        """What the privileged planner, reading the true state of every car, would do now: one
        action per agent, in the rows of the Steps."""


class Network(Protocol):
    """Where a remote simulator's arenas are."""

    @property
    def trainer(self) -> str:
        """This trainer's name on the network (the servers' status lists it)."""

    def placements(self) -> tuple[tuple[str, tuple[int, ...]], ...]:
        """Each part's server and arena ids there, in the order of the parts."""

    def losses(self) -> int:
        """How often a server was lost and its arenas reopened elsewhere."""

    def close(self) -> None:
        """Leave the network (after the engines are closed)."""


@dataclass(eq=False)
class Simulator:
    """What an environment is opened on: its engines, one per part (consecutive rows), and
    what the simulator also offers, typed (None where it has not got it)."""

    parts: tuple[Engine, ...]
    spec: BehaviourSpec
    sim_config: dict[str, Any]
    """the resolved configuration as plain nested data, a record (run records keep it): read
    :attr:`spec` for what an agent sees and drives"""
    road: Road | None = None
    network: Network | None = None

    def label_step(self, step: int) -> None:
        """Send ``step`` (the trainer's count of environment steps, >= 0) with the following
        actions: the road's world frames repeat it, so a recording of the road (a spectator's,
        or the run's own in process) lies on the trainer's ``step`` timeline."""
        if step < 0:
            raise ValueError(f"a step count must be >= 0, got {step}")
        for engine in self.parts:
            engine.trainer_step = int(step)

    def close(self) -> None:
        try:
            for engine in self.parts:
                engine.close()
        finally:
            if self.network is not None:
                self.network.close()


def spaces_from_spec(spec: BehaviourSpec) -> spaces.Dict:
    """The Dict observation space a behaviour spec describes: one Box per sensor."""
    return spaces.Dict(
        {
            o.name: spaces.Box(low=o.low, high=o.high, shape=o.shape, dtype=np.dtype(o.dtype).type)
            for o in spec.observations
        }
    )


# --- info: built here and nowhere else --------------------------------------------------------


class Faced:
    """What every face offers of its simulator."""

    simulator: Simulator

    @property
    def behaviour_spec(self) -> BehaviourSpec:
        """What an agent sees and drives (the spec the arenas were opened with)."""
        return self.simulator.spec

    @property
    def sim_config(self) -> dict[str, Any]:
        """The resolved configuration, a record: read :attr:`behaviour_spec` for what an agent
        sees and drives."""
        return self.simulator.sim_config

    def label_step(self, step: int) -> None:
        """See :meth:`Simulator.label_step`."""
        self.simulator.label_step(step)

    def _render_modes(self) -> list[str]:
        return ["rgb_array"] if self.simulator.road is not None else []


class SingleFace(Faced, ReportsEpisodeLength, gym.Env):
    """One agent on one arena: Gymnasium's ``Env`` over a simulator of one engine."""

    # Gymnasium's convention: a class attribute, replaced per instance (its render modes and
    # frame rate are the simulator's).
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(self, simulator: Simulator, render_mode: str | None = None) -> None:
        self.simulator = simulator
        self.metadata = {
            **self.metadata,
            "render_modes": self._render_modes(),
            "render_fps": 1.0 / simulator.spec.decision_period_s,
        }
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        (self._engine,) = simulator.parts
        spec = simulator.spec
        self.observation_space = spaces_from_spec(spec)
        self.action_space = spaces.Discrete(ACTION_COUNT)
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps
        self._last: StepRows | None = None

    def _unpack(self, steps: StepRows, restarted: bool) -> tuple[dict[str, np.ndarray], dict]:
        self._last = steps
        obs = {name: value[0] for name, value in steps.observations.items()}
        return obs, StepInfo.agent_of(steps, self.simulator.spec, 0, restarted=restarted)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        return self._unpack(self._engine.reset((0,), (seed,)), False)

    def step(self, action):
        if self._last is None:
            raise RuntimeError("the environment must be reset before it can step")
        actions = check_actions(action, 1, single=True)
        engine = self._engine
        restarts = engine.restarts
        engine.send(engine.agents, actions)
        steps = engine.receive()
        obs, info = self._unpack(steps, engine.restarts != restarts)
        return (
            obs,
            float(steps.reward[0]),
            bool(steps.terminated[0]),
            bool(steps.truncated[0]),
            info,
        )

    def action_masks(self) -> np.ndarray:
        """The current action mask (the name sb3-contrib's MaskablePPO looks for)."""
        if self._last is None:
            raise RuntimeError("no action mask before the first reset")
        return self._last.action_mask[0]

    # gymnasium 1.2 (which the rllib extra pins) types render with a TypeVar, 1.4 does not.
    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        road = self.simulator.road
        if self.render_mode == "rgb_array" and road is not None:
            return road.picture(0)
        return None

    def close(self) -> None:
        self.simulator.close()


class VectorFace(Faced, gym.vector.VectorEnv):
    """``num_envs`` arenas stepped together, with Gymnasium 1.x next-step autoreset: the step
    after an episode ends resets that arena (ignoring its action) and returns the first
    observation of the new episode with reward 0 and both flags false.

    A simulator of several parts (engines of consecutive environment indices,
    :attr:`part_slices`) can be stepped part by part, in the manner of EnvPool's ``send`` /
    ``recv``: :meth:`send` one part's actions, work on another part, :meth:`recv` the first.
    Each arena has its own random stream, so every part of every step is the same as in one
    part. :meth:`step` sends every part, then receives every part.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": NEXT_STEP}  # noqa: RUF012

    def __init__(self, simulator: Simulator, num_envs: int, render_mode: str | None = None) -> None:
        self.simulator = simulator
        self.metadata = {**self.metadata, "render_modes": self._render_modes()}
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        spec = simulator.spec
        self.num_envs = num_envs
        sizes = [len(engine.agents) for engine in simulator.parts]
        if sum(sizes) != num_envs:
            raise ValueError(f"the simulator's parts hold {sum(sizes)} agents, not {num_envs}")
        bounds = np.cumsum([0, *sizes])
        self.part_slices = tuple(slice(int(a), int(b)) for a, b in itertools.pairwise(bounds))
        """each part's environment indices"""
        self.single_observation_space: spaces.Dict = spaces_from_spec(spec)
        self.single_action_space = spaces.Discrete(ACTION_COUNT)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, ACTION_COUNT))
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps
        self._part_restarts: dict[int, int] = {}
        self._started = False

    def _outcome(self, steps: StepRows, restarted: bool) -> tuple[Any, ...]:
        info = StepInfo.of(steps, self.simulator.spec, restarted=restarted).vector()
        return dict(steps.observations), steps.reward, steps.terminated, steps.truncated, info

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ):
        seeds = arena_seeds(seed, self.num_envs)
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(seeds[0])
        steps = joined(
            [
                engine.reset(tuple(range(part.stop - part.start)), tuple(seeds[part]))
                for engine, part in zip(self.simulator.parts, self.part_slices, strict=True)
            ]
        )
        self._started = True
        obs, _, _, _, info = self._outcome(steps, False)
        return obs, info

    def step(self, actions):
        self._check_started()
        actions = check_actions(actions, self.num_envs, single=False)
        parts = self.simulator.parts
        restarts = [engine.restarts for engine in parts]
        for engine, part in zip(parts, self.part_slices, strict=True):
            engine.send(engine.agents, actions[part])
        whole = joined([engine.receive() for engine in parts])
        return self._outcome(whole, [engine.restarts for engine in parts] != restarts)

    def send(self, part: int, actions: np.ndarray) -> None:
        """Part ``part``'s actions (one per environment of :attr:`part_slices` [part]) go
        out: a server plays the round while the caller works (in process it is played here,
        before this returns). :meth:`recv` takes it."""
        self._check_started()
        part_slice = self._part_slice(part)
        actions = check_actions(actions, part_slice.stop - part_slice.start, single=False)
        engine = self.simulator.parts[part]
        self._part_restarts[part] = engine.restarts
        engine.send(engine.agents, actions)

    def recv(self, part: int):
        """The step of part ``part`` that :meth:`send` started: ``(observations, rewards,
        terminated, truncated, info)`` of its environments, as :meth:`step` returns them for
        all."""
        self._part_slice(part)
        engine = self.simulator.parts[part]
        steps = engine.receive()
        return self._outcome(
            steps, engine.restarts != self._part_restarts.get(part, engine.restarts)
        )

    @property
    def restorable(self) -> bool:
        """Whether its arenas can be kept and put back (:class:`Restorable`)."""
        return all(isinstance(e, Restorable) and e.restorable for e in self.simulator.parts)

    def snapshot(self) -> tuple[dict[str, Any], ...]:
        """Every arena between steps, a snapshot per part, for :meth:`restore`."""
        self._check_started()
        return tuple(engine.snapshot() for engine in self._restorable())

    def restore(self, snapshots: Sequence[Mapping[str, Any]]) -> None:
        """Every arena back as :meth:`snapshot` found it (no reset needed to step on)."""
        for engine, snapshot in zip(self._restorable(), snapshots, strict=True):
            engine.restore(snapshot)
        self._started = True

    def _restorable(self) -> list[Restorable]:
        if not self.restorable:
            raise TypeError("arenas are kept in process, or opened alone on a 1.8 server")
        return [engine for engine in self.simulator.parts if isinstance(engine, Restorable)]

    def _check_started(self) -> None:
        if not self._started:
            raise RuntimeError("the environment must be reset before it can step")

    def _part_slice(self, part: int) -> slice:
        if not 0 <= part < len(self.part_slices):
            raise ValueError(
                f"part must be between 0 and {len(self.part_slices) - 1} "
                f"(this environment has {len(self.part_slices)} part(s)), got {part}"
            )
        return self.part_slices[part]

    def render(self) -> tuple[np.ndarray, ...] | None:  # type: ignore[override, unused-ignore]
        road = self.simulator.road
        if self.render_mode == "rgb_array" and road is not None:
            return tuple(road.picture(i) for i in range(self.num_envs))
        return None

    def close_extras(self, **kwargs: Any) -> None:
        # A constructor that raised (no server, every server full) leaves nothing to close;
        # gymnasium's __del__ calls close all the same.
        simulator = getattr(self, "simulator", None)
        if simulator is not None:
            simulator.close()


__all__ = [
    "Engine",
    "Faced",
    "Network",
    "Restorable",
    "Road",
    "Simulator",
    "SingleFace",
    "StepInfo",
    "StepRows",
    "VectorFace",
    "joined",
    "spaces_from_spec",
]

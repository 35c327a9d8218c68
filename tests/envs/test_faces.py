"""One environment over two engines (issue 45): the faces read only Steps, their info comes from
one typed record, and what a simulator also offers is a typed property of it."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from overtake.envs.faces import Simulator, StepInfo, VectorFace
from overtake.protocol.vocabulary import EPISODE_COUNTS, INFO_KEYS
from overtake.server.engine.env import HighwayEnv, HighwayVectorEnv
from overtake.server.engine.local import IN_PROCESS, LocalEngine, LocalRoad
from overtake.server.engine.parallel_env import HighwayParallelEnv
from overtake.server.sim import make_config

ROOT = Path(__file__).resolve().parents[2]
SHORT = {"episode.max_decisions": 12, "traffic.density": "heavy", "camera.enabled": False}


def _keys_within_the_vocabulary(info: dict) -> None:
    assert set(info) - {"_metrics"} <= set(INFO_KEYS), set(info)


def test_every_face_says_the_same_info_keys_and_nothing_else():
    """Single, vector and PettingZoo faces: the keys of INFO_KEYS, the event counts agreeing
    with the metrics where an episode ended."""
    single = HighwayEnv(overrides=SHORT)
    vector = HighwayVectorEnv(3, overrides=SHORT)
    parallel = HighwayParallelEnv(agents=2, overrides=SHORT)
    infos: list[dict] = [single.reset(seed=1)[1], vector.reset(seed=1)[1]]
    infos += parallel.reset(seed=1)[1].values()
    ended_seen = 0
    for _ in range(SHORT["episode.max_decisions"]):
        *_, info = single.step(1)
        infos.append(info)
        *_, info = vector.step(np.ones(3, dtype=np.int64))
        infos.append(info)
        *_, parallel_infos = parallel.step({a: 1 for a in parallel.agents})
        infos += parallel_infos.values()
    for info in infos:
        _keys_within_the_vocabulary(info)
        assert set(info["episode_counts"]) == set(EPISODE_COUNTS)
        if "metrics" in info:
            ended_seen += 1
            ended = info.get("_metrics", True)
            for name in EPISODE_COUNTS:
                assert np.array_equal(
                    np.asarray(info["episode_counts"][name])[ended],
                    np.asarray(info["metrics"][name])[ended],
                )
    assert ended_seen >= 3  # the time limit ended every face's episodes


def test_step_info_fields_are_the_vocabulary():
    names = tuple(f.name for f in dataclasses.fields(StepInfo))
    # Beyond the info's keys: where episodes ended, and the rows and spec an agent's is read from.
    assert names[: len(INFO_KEYS)] == INFO_KEYS
    assert names[len(INFO_KEYS) :] == ("ended", "rows", "spec")


def test_an_in_process_vector_env_in_parts_is_the_env_in_one_part():
    """The face steps any simulator's parts, in process too: two engines of 2 and 3 arenas
    send and receive part by part, and equal one engine of 5 step by step."""
    config = make_config("min2018", SHORT)
    whole = HighwayVectorEnv(5, config=config)
    engines = (LocalEngine(config, 2), LocalEngine(config, 3))
    parts = VectorFace(
        Simulator(parts=engines, spec=engines[0].spec, sim_config=whole.sim_config), 5
    )
    assert parts.part_slices == (slice(0, 2), slice(2, 5))
    rng = np.random.default_rng(4)
    got, want = parts.reset(seed=3), whole.reset(seed=3)
    for step in range(30):
        for key in want[0]:
            np.testing.assert_array_equal(got[0][key], want[0][key], err_msg=f"{step} {key}")
        actions = rng.integers(0, 5, size=5)
        want = whole.step(actions)
        # Part 1 first, then part 0: each arena has its own random stream.
        parts.send(1, actions[2:])
        parts.send(0, actions[:2])
        second, first = parts.recv(1), parts.recv(0)
        got = tuple(
            {k: np.concatenate([first[i][k], second[i][k]]) for k in first[i]}
            if i == 0
            else np.concatenate([first[i], second[i]])
            for i in range(4)
        ) + (first[4],)
        for i in (1, 2, 3):
            np.testing.assert_array_equal(got[i], want[i])


@pytest.mark.parametrize("make", [lambda: HighwayEnv(overrides=SHORT), lambda: HighwayVectorEnv(2)])
def test_stepping_before_reset_is_refused_by_every_face(make):
    env = make()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0 if isinstance(env, HighwayEnv) else np.zeros(2, dtype=np.int64))


def test_the_in_process_road_is_the_servers_world_frame():
    """What the in-process simulator shows of its road is what a server's spectator sees: the
    group's world frame, with the trainer's step label sent with the actions."""
    envs = HighwayVectorEnv(2, overrides=SHORT)
    road = envs.simulator.road
    assert isinstance(road, LocalRoad) and envs.simulator.network is None
    envs.reset(seed=2)
    envs.label_step(41)
    obs, reward, _, _, info = envs.step(np.array([1, 3]))
    frame = road.world_frame(1)
    assert (frame.server, frame.arena, frame.trainer_step) == (IN_PROCESS, 1, 41)
    np.testing.assert_array_equal(frame.observations["lidar"][0], obs["lidar"][1])
    assert frame.reward[0] == reward[1] and frame.action_applied[0] == info["action_applied"][1]
    picture = road.picture(0)
    assert picture.ndim == 3 and picture.shape[2] == 3
    assert road.planner_actions().shape == (2,)


def test_no_caller_reaches_through_unwrapped():
    """client/ and trainers/ ask a face's simulator what it offers: none reaches through
    Gymnasium's ``.unwrapped`` (tests may)."""
    reaching = []
    for folder in ("client", "trainers"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute) and node.attr == "unwrapped":
                    reaching.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert reaching == []


def test_one_agent_s_info_read_from_its_row_is_the_vector_info_s_row():
    """A single environment reads its info straight from the Steps' row
    (``StepInfo.agent_of``): the same dict as the vector's info taken apart, for steps that
    ended, went on, were late or saw the server restart, with the lane-change watch's counts."""
    config = make_config("min2018", {**SHORT, "ego.lane_change_watch": True})
    engine = LocalEngine(config, 3)
    spec = engine.spec
    steps = engine.reset((0, 1, 2), (5, 6, 7))
    rng = np.random.default_rng(2)
    ended = late = 0
    for step in range(2 * SHORT["episode.max_decisions"]):
        # Leave arena 1's car out now and then: its agent is late.
        agents = engine.agents if step % 3 else engine.agents[[0, 2]]
        engine.send(agents, rng.integers(0, 5, size=agents.size))
        steps = engine.receive()
        for row in range(3):
            for restarted in (False, True):
                want = StepInfo.of(steps, spec, restarted=restarted).agent(row)
                got = StepInfo.agent_of(steps, spec, row, restarted=restarted)
                assert got.keys() == want.keys()
                for key, value in want.items():
                    np.testing.assert_equal(got[key], value, err_msg=f"{step} {row} {key}")
                    assert type(got[key]) is type(value)
        ended += int(steps.ended.sum())
        late += int(steps.late.sum())
    assert ended >= 3 and late >= 3  # the time limit ended episodes; arena 1 was left out


def test_an_unsupported_render_mode_is_refused_naming_what_there_is():
    from overtake.envs.registry import check_render_mode

    check_render_mode(None, [])
    check_render_mode("rgb_array", ["rgb_array"])
    with pytest.raises(ValueError, match=r"one of \['rgb_array'\] or None, got 'human'"):
        check_render_mode("human", ["rgb_array"])
    with pytest.raises(ValueError, match="does not render; watch it with a spectator"):
        check_render_mode("rgb_array", [])

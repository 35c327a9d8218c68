"""ML-Agents' own code on overtake: mlagents-envs 1.1.0's wrappers drive ``RemoteEnvironment``
against a real server, unchanged, and overtake's look-alike types carry every public name of
ML-Agents' own.

mlagents-envs declares Python <= 3.10; ``scripts/setup-mlagents.sh`` installs it (without its
dependencies) with protobuf 3.20.3, gym 0.26 and pettingzoo. Where it is not installed these
tests skip, saying so.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from overtake.client.mlagents import environment as ours
from overtake.client.mlagents.environment import RemoteEnvironment, UnsupportedRequest
from overtake.server.engine.env import HighwayVectorEnv

from tests.support.remote import remote_config

base_env = pytest.importorskip(
    "mlagents_envs.base_env",
    reason="mlagents-envs is not installed (scripts/setup-mlagents.sh installs it)",
)
pytest.importorskip("gym", reason="gym 0.26 is not installed (scripts/setup-mlagents.sh)")
pytest.importorskip("pettingzoo", reason="pettingzoo is not installed (scripts/setup-mlagents.sh)")

from overtake.client.mlagents.wrappers import load_wrappers  # noqa: E402

WRAPPERS = load_wrappers()
# mlagents-envs 1.1.0's generated protobuf modules use descriptor calls protobuf deprecates.
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning:mlagents_envs.*")
# Episodes of 12 decisions on a road of 10 cars, which these actions live through.
SHORT = {"episode.max_decisions": 12, "traffic.vehicle_count": 10}


def as_mlagents(batch: np.ndarray) -> np.ndarray:
    """An in-process observation batch as ML-Agents delivers Unity's (written out here)."""
    out = batch.astype(np.float32) / np.float32(255.0) if batch.dtype == np.uint8 else batch
    out = out.astype(np.float32)
    return out[:, None] if out.ndim == 3 else out  # channels first, as mlagents-envs 1.1.0


# --- the types carry ML-Agents' names ---------------------------------------------------------


def public_names(cls: type) -> set[str]:
    return {n for n in dir(cls) if not n.startswith("_")} - {"count", "index"}


@pytest.mark.parametrize(
    "name",
    [
        "ActionSpec",
        "ActionTuple",
        "BehaviorSpec",
        "ObservationSpec",
        "DecisionSteps",
        "TerminalSteps",
        "DimensionProperty",
        "ObservationType",
    ],
)
def test_every_public_name_of_ml_agents_types_is_on_ours(name):
    theirs, mine = getattr(base_env, name), getattr(ours, name)
    missing = public_names(theirs) - public_names(mine)
    assert not missing, f"{name} lacks {sorted(missing)}"
    if hasattr(theirs, "_fields"):
        assert mine._fields == theirs._fields
    if issubclass(theirs, (base_env.DimensionProperty, base_env.ObservationType)):
        assert {m.name: m.value for m in theirs} == {m.name: m.value for m in mine}


def test_remote_environment_has_every_method_of_base_env():
    for method in ("step", "reset", "close", "set_actions", "set_action_for_agent", "get_steps"):
        theirs = inspect.signature(getattr(base_env.BaseEnv, method))
        mine = inspect.signature(getattr(RemoteEnvironment, method))
        # ML-Agents' positional parameters come first, in the same order (ours may add
        # keyword ones, such as reset's seed).
        assert list(mine.parameters)[: len(theirs.parameters)] == list(theirs.parameters)
    assert isinstance(inspect.getattr_static(RemoteEnvironment, "behavior_specs"), property)


def test_ml_agents_isinstance_checks_take_ours():
    # UnityToGymWrapper ends an episode on isinstance(steps, TerminalSteps) with its own class.
    spec = ours.BehaviorSpec(
        [ours.mlagents_observation_spec("ego", (6,))], ours.ActionSpec.create_discrete((5,))
    )
    assert isinstance(ours.TerminalSteps.empty(spec), base_env.TerminalSteps)
    assert not isinstance(ours.TerminalSteps.empty(spec), base_env.DecisionSteps)
    assert isinstance(ours.DecisionSteps.empty(spec), base_env.DecisionSteps)
    assert issubclass(RemoteEnvironment, base_env.BaseEnv)


# --- UnityToGymWrapper ------------------------------------------------------------------------


@pytest.mark.timeout(60)
def test_unity_to_gym_wrapper_drives_the_remote_environment_as_in_process(shared_server):
    server = shared_server
    remote = RemoteEnvironment(
        seed=5, overrides=SHORT, config=remote_config(server.endpoint, server.name)
    )
    env = WRAPPERS.gym(remote, allow_multiple_obs=True)
    local = HighwayVectorEnv(num_envs=1, overrides=SHORT)
    try:
        # The camera is a visual observation (1, 80, 80); ego and LIDAR one vector, in the
        # behaviour's order (camera, ego, lidar).
        assert env.action_space.n == 5
        camera_space, vector_space = env.observation_space.spaces
        assert camera_space.shape == (1, 80, 80) and vector_space.shape == (6 + 360,)

        def expected(obs: dict[str, np.ndarray]) -> list[np.ndarray]:
            return [
                as_mlagents(obs["camera"])[0],
                np.concatenate([obs["ego"][0], obs["lidar"][0]]).astype(np.float32),
            ]

        local.reset(seed=5)  # the arena as opened
        local.reset()  # the wrapper resets once when it is made, continuing the stream
        local_obs, _ = local.reset()
        observation = env.reset()
        for got, want in zip(observation, expected(local_obs), strict=True):
            np.testing.assert_array_equal(got, want)
        actions = [1, 1, 3, 0, 2, 4, 0, 1, 1, 3, 0, 0]
        ended_at = None
        for step, action in enumerate(actions, start=1):
            observation, reward, done, info = env.step(action)
            local_obs, local_reward, terminated, truncated, _ = local.step(np.array([action]))
            for got, want in zip(observation, expected(local_obs), strict=True):
                np.testing.assert_array_equal(got, want)
            assert reward == np.float32(local_reward[0])
            assert done == bool(terminated[0] or truncated[0])
            if done:
                ended_at = step
                break
        assert ended_at == SHORT["episode.max_decisions"]
        assert info["step"].interrupted[0]  # the time limit, as ML-Agents marks it
        assert len(env.reset()) == 2  # and a new episode
    finally:
        env.close()
        local.close()
    assert server.status().arenas_used == 0


# --- PettingZoo: several learning cars on one road --------------------------------------------


@pytest.mark.timeout(60)
def test_unity_parallel_env_drives_two_cars_on_a_shared_road(shared_server):
    server = shared_server
    remote = RemoteEnvironment(
        arenas=1,
        agents_per_arena=2,
        seed=3,
        overrides=SHORT,
        config=remote_config(server.endpoint, server.name),
    )
    env = WRAPPERS.parallel(remote, seed=0)
    try:
        observations = env.reset()
        agents = env.agents
        assert agents == [f"{remote.behavior_name}?agent_id={i}" for i in (0, 1)]
        assert set(observations) == set(agents)
        for agent in agents:
            # Deciding agents come with ML-Agents' action mask (True: can NOT be taken).
            assert set(observations[agent]) == {"observation", "action_mask"}
            assert [o.shape for o in observations[agent]["observation"]] == [
                (1, 80, 80),
                (6,),
                (360,),
            ]
            assert observations[agent]["action_mask"][0].dtype == bool
        positions = []
        rng = np.random.default_rng(0)
        for _ in range(SHORT["episode.max_decisions"]):
            actions = {agent: int(rng.integers(0, 3)) for agent in env.agents}
            observations, rewards, dones, infos = env.step(actions)
            assert set(rewards) >= set(actions)
            positions.append(remote.steps.observations["ego"].copy())
            if any(dones.values()):
                break
        assert all(dones.values()), "both cars reach the time limit together"
        assert all(infos[a]["interrupted"] for a in dones)
        # Two cars of one arena: one road, two different views of it.
        assert not np.array_equal(positions[-1][0], positions[-1][1])
    finally:
        env.close()
    assert server.status().arenas_used == 0


@pytest.mark.timeout(60)
def test_unity_aec_env_takes_turns_over_the_cars(shared_server):
    server = shared_server
    remote = RemoteEnvironment(
        arenas=2,
        agents_per_arena=1,
        seed=4,
        overrides=SHORT,
        config=remote_config(server.endpoint, server.name),
    )
    env = WRAPPERS.aec(remote, seed=0)
    try:
        env.reset()
        assert len(env.agents) == 2
        turns = 0
        seen = set()
        for agent in env.agent_iter(max_iter=2 * 5):
            _, _, done, _ = env.last()
            seen.add(agent)
            env.step(None if done else 1)
            turns += 1
        assert turns == 10 and seen == set(env.possible_agents)
        assert remote.steps.action_applied.tolist() == [1, 1]  # both cars accelerated
    finally:
        env.close()
    assert server.status().arenas_used == 0


# --- what overtake has not got ----------------------------------------------------------------


def test_a_side_channel_is_refused_with_what_is_supported():
    from mlagents_envs.side_channel.engine_configuration_channel import (
        EngineConfigurationChannel,
    )

    with pytest.raises(UnsupportedRequest) as caught:
        RemoteEnvironment("tcp/127.0.0.1:9", side_channels=[EngineConfigurationChannel()])
    message = str(caught.value)
    assert "EngineConfigurationChannel" in message and "overrides" in message


@pytest.mark.timeout(60)
def test_continuous_actions_from_ml_agents_are_refused_by_name(shared_server):
    server = shared_server
    env = RemoteEnvironment(config=remote_config(server.endpoint, server.name))
    try:
        action = base_env.ActionTuple(continuous=np.zeros((1, 2), dtype=np.float32))
        with pytest.raises(UnsupportedRequest, match=r"discrete only .* shape \(1, 2\)"):
            env.set_actions(env.behavior_name, action)
        # ML-Agents' own ActionTuple with discrete actions is taken.
        env.set_actions(env.behavior_name, base_env.ActionTuple(discrete=np.array([[4]])))
        env.step()
        assert env.steps.action_applied.tolist() in ([4], [0])  # right, or keep if masked
    finally:
        env.close()

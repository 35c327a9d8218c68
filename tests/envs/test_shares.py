"""Shares of one in-process engine (``overtake.envs.shares``): a share's arenas step, keep and
come back exactly as an engine of their own would, a share that sends nothing sits the round
out untouched, and misuse is refused."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.envs.shares import share_face
from overtake.protocol.vocabulary import ACTION_COUNT, EPISODE_LENGTH_SETTING
from overtake.server.engine.env import HighwayVectorEnv

# A short episode, so that the shares' arenas end and restart (next-step autoreset) in the test.
SHORT = {EPISODE_LENGTH_SETTING: 7}


def _assert_same(a: tuple, b: tuple) -> None:
    obs_a, reward_a, term_a, trunc_a, info_a = a
    obs_b, reward_b, term_b, trunc_b, info_b = b
    assert obs_a.keys() == obs_b.keys()
    for name in obs_a:
        np.testing.assert_array_equal(obs_a[name], obs_b[name], err_msg=name)
    np.testing.assert_array_equal(reward_a, reward_b)
    np.testing.assert_array_equal(term_a, term_b)
    np.testing.assert_array_equal(trunc_a, trunc_b)
    assert info_a.keys() == info_b.keys()
    for key, value in info_a.items():
        if isinstance(value, dict):
            assert value.keys() == info_b[key].keys()
            for name, column in value.items():
                np.testing.assert_array_equal(column, info_b[key][name], err_msg=f"{key}.{name}")
        else:
            np.testing.assert_array_equal(value, info_b[key], err_msg=key)


def _assert_snapshots_equal(a: dict, b: dict) -> None:
    assert a["sim"]["config_json"] == b["sim"]["config_json"]
    assert a["sim"]["rng_states_json"] == b["sim"]["rng_states_json"]
    np.testing.assert_array_equal(a["sim"]["needs_reset"], b["sim"]["needs_reset"])
    assert a["sim"]["arrays"].keys() == b["sim"]["arrays"].keys()
    for name, value in a["sim"]["arrays"].items():
        np.testing.assert_array_equal(value, b["sim"]["arrays"][name], err_msg=name)
    for name, value in a["slots"].items():
        np.testing.assert_array_equal(value, b["slots"][name], err_msg=name)


def _step_alike(shares, lone, rng: np.random.Generator, rounds: int) -> None:
    """``rounds`` rounds of the same random actions: every share sends before any receives,
    and each share's step is its lone engine's."""
    for _ in range(rounds):
        actions = [rng.integers(0, ACTION_COUNT, size=s.num_envs) for s in shares]
        for share, act in zip(shares, actions, strict=True):
            share.send(0, act)
        for share, alone, act in zip(shares, lone, actions, strict=True):
            _assert_same(share.recv(0), alone.step(act))


def _faces(preset: str, arenas: tuple[int, ...]):
    whole = HighwayVectorEnv(num_envs=sum(arenas), preset=preset, overrides=SHORT)
    shares = share_face(whole, arenas)
    lone = [HighwayVectorEnv(num_envs=n, preset=preset, overrides=SHORT) for n in arenas]
    return shares, lone


@pytest.mark.parametrize("preset", ["highway-fast", "ho2018", "fayjie2018", "min2018"])
def test_a_share_steps_as_an_engine_of_its_own(preset: str) -> None:
    """Every share's rows, step by step through episode ends, and its snapshot, are those of
    an engine of its arenas alone given the same seeds and actions."""
    shares, lone = _faces(preset, (2, 1, 3))
    rng = np.random.default_rng(7)
    try:
        for k, (share, alone) in enumerate(zip(shares, lone, strict=True)):
            seeds = [100 * k + i for i in range(share.num_envs)]
            (obs_share, _), (obs_alone, _) = share.reset(seed=seeds), alone.reset(seed=seeds)
            for name in obs_alone:
                np.testing.assert_array_equal(obs_share[name], obs_alone[name], err_msg=name)
        _step_alike(shares, lone, rng, 16)
        for share, alone in zip(shares, lone, strict=True):
            _assert_snapshots_equal(share.snapshot()[0], alone.snapshot()[0])
    finally:
        for env in (*shares, *lone):
            env.close()


def test_snapshots_move_between_a_share_and_an_engine_of_its_own() -> None:
    """A lone engine's snapshot restored into a share (and a share's into a lone engine) plays
    on as the engine it was taken from."""
    shares, lone = _faces("highway-fast", (1, 2))
    rng = np.random.default_rng(3)
    try:
        for share, alone in zip(shares, lone, strict=True):
            share.reset(seed=list(range(share.num_envs)))
            alone.reset(seed=[50 + i for i in range(alone.num_envs)])
        for _ in range(5):
            for alone in lone:
                alone.step(rng.integers(0, ACTION_COUNT, size=alone.num_envs))
        # Share 1 takes lone engine 1's arenas; lone engine 0 takes share 0's.
        shares[1].restore(lone[1].snapshot())
        lone[0].restore(shares[0].snapshot())
        _step_alike(shares, lone, rng, 10)
    finally:
        for env in (*shares, *lone):
            env.close()


def test_a_share_that_sends_nothing_sits_the_round_out() -> None:
    """Rounds played without share 1's actions leave its arenas exactly as they were; it then
    steps on as an engine that was not stepped meanwhile."""
    shares, lone = _faces("highway-fast", (2, 2))
    rng = np.random.default_rng(11)
    try:
        for share, alone in zip(shares, lone, strict=True):
            share.reset(seed=[1, 2])
            alone.reset(seed=[1, 2])
        before = shares[1].snapshot()[0]
        for _ in range(4):
            act = rng.integers(0, ACTION_COUNT, size=2)
            shares[0].send(0, act)
            _assert_same(shares[0].recv(0), lone[0].step(act))
        _assert_snapshots_equal(shares[1].snapshot()[0], before)
        _step_alike(shares, lone, rng, 3)
    finally:
        for env in (*shares, *lone):
            env.close()


def test_misuse_of_a_share_is_refused() -> None:
    shares, lone = _faces("highway-fast", (1, 1))
    try:
        for share in shares:
            share.reset(seed=[0])
        engine = shares[0].simulator.parts[0]
        with pytest.raises(RuntimeError, match="no actions sent"):
            engine.receive()
        engine.send(engine.agents, np.array([1]))
        with pytest.raises(RuntimeError, match="sent twice"):
            engine.send(engine.agents, np.array([1]))
        with pytest.raises(RuntimeError, match="between rounds"):
            shares[0].snapshot()
        with pytest.raises(ValueError, match="agents are 0..0"):
            shares[1].simulator.parts[0].send(np.array([1]), np.array([1]))
        with pytest.raises(ValueError, match="arenas 0..0"):
            shares[1].simulator.parts[0].reset((1,), (None,))
        whole = HighwayVectorEnv(num_envs=3, preset="highway-fast")
        with pytest.raises(ValueError, match="do not fill"):
            share_face(whole, (1, 1))
        with pytest.raises(ValueError, match="at least one arena"):
            share_face(whole, ())
        whole.close()
    finally:
        for env in (*shares, *lone):
            env.close()


def test_the_engine_closes_with_its_last_share() -> None:
    shares, lone = _faces("highway-fast", (1, 1))
    for env in lone:
        env.close()
    closed = []
    engine = shares[0].simulator.parts[0].shared.engine  # type: ignore[attr-defined]
    engine.close = lambda: closed.append(True)
    shares[0].close()
    assert closed == []
    shares[1].close()
    assert closed == [True]

"""A simulator's snapshot, restored, goes on exactly as the simulator it was taken from: for
every preset, through episode ends and autoresets, in a fresh environment."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from overtake.server.engine.env import HighwayVectorEnv
from overtake.server.sim import PRESETS, HighwaySim
from overtake.server.sim.presets import make_config
from overtake.server.sim.snapshot import SnapshotMismatch

# Short episodes, so that the steps after the snapshot cross ends and autoresets.
SHORT = {"episode.max_decisions": 7}


def _play(env, actions):
    out = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        out.append((obs, reward, terminated, truncated, info["action_mask"], info))
    return out


def _same(a, b):
    for (obs_a, r_a, t_a, u_a, m_a, info_a), (obs_b, r_b, t_b, u_b, m_b, info_b) in zip(
        a, b, strict=True
    ):
        for key in obs_a:
            np.testing.assert_array_equal(obs_a[key], obs_b[key])
        np.testing.assert_array_equal(r_a, r_b)
        np.testing.assert_array_equal(t_a, t_b)
        np.testing.assert_array_equal(u_a, u_b)
        np.testing.assert_array_equal(m_a, m_b)
        for name, value in info_a.get("metrics", {}).items():
            np.testing.assert_array_equal(value, info_b["metrics"][name])


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_a_restored_snapshot_steps_on_as_the_simulator_it_was_taken_from(preset):
    rng = np.random.default_rng(5)
    before = rng.integers(0, 5, (9, 3))
    after = rng.integers(0, 5, (12, 3))
    env = HighwayVectorEnv(3, preset=preset, overrides=SHORT)
    env.reset(seed=11)
    _play(env, before)
    snapshot = env.snapshot()
    expected = _play(env, after)
    env.close()

    other = HighwayVectorEnv(3, preset=preset, overrides=SHORT)
    other.reset(seed=99)  # another road entirely: the restore replaces all of it
    _play(other, before[:3])
    other.restore(snapshot)
    _same(expected, _play(other, after))
    # Never reset at all: a restore is enough to step.
    fresh = HighwayVectorEnv(3, preset=preset, overrides=SHORT)
    fresh.restore(snapshot)
    _same(expected, _play(fresh, after))
    other.close()
    fresh.close()


def test_a_snapshot_fits_only_its_own_configuration_and_size():
    env = HighwayVectorEnv(2, preset="min2018", overrides={"traffic.density": "light"})
    env.reset(seed=1)
    snapshot = env.snapshot()
    heavy = HighwayVectorEnv(2, preset="min2018", overrides={"traffic.density": "heavy"})
    with pytest.raises(
        SnapshotMismatch, match="traffic.density: 'light' in the snapshot, 'heavy' here"
    ):
        heavy.restore(snapshot)
    three = HighwayVectorEnv(3, preset="min2018", overrides={"traffic.density": "light"})
    with pytest.raises(SnapshotMismatch, match=r"\(3, "):
        three.restore(snapshot)
    with pytest.raises(ValueError, match="zip"):
        env.restore(snapshot * 2)
    for e in (env, heavy, three):
        e.close()


def _without(config_json: str, dotted: str) -> str:
    """The configuration as an older code's snapshot holds it: without the setting
    ``dotted`` (added since)."""
    config = json.loads(config_json)
    *sections, name = dotted.split(".")
    holder = config
    for section in sections:
        holder = holder[section]
    del holder[name]
    return json.dumps(config)


def test_a_snapshot_of_older_code_restores_where_what_was_added_since_changes_nothing():
    """A run stopped by one version of the code resumes exactly on a later one that only
    added settings (their values now those in effect before, settings_history): the
    snapshot restores and steps on as the simulator it was taken from. Where an added
    setting changed what the arenas do (ho2018's applied_as_driven, on since issue 66) it is
    refused, naming the setting."""
    sim = HighwaySim(make_config("min2018", SHORT), num_arenas=2)
    sim.reset(seeds=[3, 4])
    snapshot = sim.snapshot()
    older = dataclasses.replace(
        snapshot, config_json=_without(snapshot.config_json, "highway_scene.ego_driver")
    )
    actions = np.ones((2, 1), dtype=np.int64)
    expected = [sim.step(actions) for _ in range(3)]
    again = HighwaySim(make_config("min2018", SHORT), num_arenas=2)
    again.restore(older)
    for want in expected:
        got = again.step(actions)
        np.testing.assert_array_equal(got.reward, want.reward)
        np.testing.assert_array_equal(got.terminated, want.terminated)
    for name, value in sim.state.__dict__.items():
        np.testing.assert_array_equal(getattr(again.state, name), value, err_msg=name)
    ho = HighwaySim(make_config("ho2018", SHORT), num_arenas=1)
    ho.reset(seeds=[5])
    taken = ho.snapshot()
    before_66 = dataclasses.replace(
        taken, config_json=_without(taken.config_json, "ego.applied_as_driven")
    )
    with pytest.raises(SnapshotMismatch, match="ego.applied_as_driven: absent from the snapshot"):
        HighwaySim(make_config("ho2018", SHORT), num_arenas=1).restore(before_66)


SPAWNER_SETTINGS = (
    "traffic.spawner_count",
    "traffic.spawner_step_s",
    "traffic.spawner_wait_s",
    "traffic.spawner_ahead_share",
    "traffic.spawner_clearance_m",
    "traffic.spawner_clearance_lanes",
)


def test_a_snapshot_of_before_the_spawners_restores_where_none_runs_and_not_on_min2018s():
    """Issue 68 added the spawners' settings and their clocks to the state: a snapshot of
    older code has neither. On a treadmill (fayjie2018) or Ho's entry nothing of them runs,
    and the snapshot restores and steps on as its simulator; min2018's traffic itself
    changed (its treadmill is now its authors' spawners), and its snapshot is refused."""
    for preset in ("fayjie2018", "ho2018"):
        sim = HighwaySim(make_config(preset, SHORT), num_arenas=2)
        sim.reset(seeds=[3, 4])
        taken = sim.snapshot()
        config_json = taken.config_json
        for name in SPAWNER_SETTINGS:
            config_json = _without(config_json, name)
        arrays = {k: v for k, v in taken.arrays.items() if k != "spawner_wait_s"}
        older = dataclasses.replace(taken, config_json=config_json, arrays=arrays)
        actions = np.ones((2, 1), dtype=np.int64)
        expected = [sim.step(actions) for _ in range(3)]
        again = HighwaySim(make_config(preset, SHORT), num_arenas=2)
        again.restore(older)
        for want in expected:
            np.testing.assert_array_equal(again.step(actions).reward, want.reward)
        for name, value in sim.state.__dict__.items():
            np.testing.assert_array_equal(getattr(again.state, name), value, err_msg=name)
    treadmill = HighwaySim(
        make_config("min2018", {**SHORT, "traffic.entry": "comfortable"}), num_arenas=1
    )
    treadmill.reset(seeds=[5])
    taken = treadmill.snapshot()
    config = json.loads(taken.config_json)
    for name in SPAWNER_SETTINGS:
        del config["traffic"][name.split(".")[1]]
    older = dataclasses.replace(
        taken,
        config_json=json.dumps(config),
        arrays={k: v for k, v in taken.arrays.items() if k != "spawner_wait_s"},
    )
    with pytest.raises(
        SnapshotMismatch, match="traffic.entry: 'comfortable' in the snapshot, 'spawners' here"
    ):
        HighwaySim(make_config("min2018", SHORT), num_arenas=1).restore(older)

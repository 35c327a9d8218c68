"""One scenario for every command (issue 45): which simulator and where are typed once
(client/episodes/scenario.py), every command's configuration is one, and the densities are
spelled once (the contract's vocabulary)."""

from __future__ import annotations

import dataclasses
import json
import re
import typing
from pathlib import Path

import numpy as np
import pytest

from overtake.cli import UsageError
from overtake.client.episodes.drive import DriveConfig
from overtake.client.episodes.drive import main as drive
from overtake.client.episodes.records import read_records
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.episodes.session import Driver, Episodes, Keeping, drive_episodes
from overtake.client.mlagents.unity_bridge import BridgeConfig
from overtake.protocol.vocabulary import DENSITIES
from overtake.trainers.config.train_config import TrainConfig
from overtake.trainers.episode_replay import ReplayConfig
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.experiment.plan import ExperimentConfig

ROOT = Path(__file__).resolve().parents[2]
SCENARIO_FIELDS = {f.name for f in dataclasses.fields(Scenario)}
WHERE_FIELDS = {f.name for f in dataclasses.fields(Where)}


@pytest.mark.parametrize(
    "command, kind",
    [
        (DriveConfig, Scenario),
        (EvalConfig, Scenario),
        (TrainConfig, Scenario),
        (BridgeConfig, Scenario),
        (ReplayConfig, Where),
        (ExperimentConfig, Where),
    ],
)
def test_every_command_takes_the_one_scenario(command, kind):
    """Each command's configuration holds a Scenario and a Where (or, where the record or the
    paper says which simulator, a Where only) as fields, and declares none of their fields
    again: the same flags in every command, typed once."""
    hints = typing.get_type_hints(command)
    assert hints["where"] is Where
    assert ("scenario" in hints) == (kind is Scenario)
    own = set(hints) - {"scenario", "where"}
    # (An experiment's --set is its own: overrides of its paper's scenario, for every run.)
    again = own & (SCENARIO_FIELDS | WHERE_FIELDS if kind is Scenario else WHERE_FIELDS)
    assert not again, again


def test_a_scenario_names_its_overrides_after_the_base_and_set():
    scenario = Scenario(
        traffic="heavy", max_decisions=30, set=("traffic.density=light", "road.lane_count=4")
    )
    assert scenario.overrides({"camera.enabled": False, "road.lane_count": 7}) == {
        "camera.enabled": False,
        "road.lane_count": 4,  # --set over the base
        "traffic.density": "heavy",  # --traffic over --set
        "episode.max_decisions": 30,
    }
    assert Scenario().overrides() == {}
    assert Scenario(preset="ho2018").preset_or("fayjie2018") == "ho2018"
    assert Scenario().preset_or("fayjie2018") == "fayjie2018"
    assert Scenario().preset_or(None) == "min2018"
    with pytest.raises(UsageError, match="dotted.name=value"):
        Scenario(set=("no-equals",)).overrides()


def test_a_command_s_scenario_and_where_are_its_own_fields():
    config = EvalConfig(
        policy="idle",
        scenario=Scenario(preset="ho2018", traffic="light"),
        where=Where(connect=("tcp/h:1",)),
    )
    assert config.scenario.preset_or(None) == "ho2018" and not config.where.in_process
    # Where is carried into another command's configuration whole, the scenario stays its own.
    moved = dataclasses.replace(TrainConfig(), where=config.where)
    assert moved.where.connect == ("tcp/h:1",) and moved.preset == "min2018"
    # Every command spells these options the same: the same flags, from the same two types.
    for command in (TrainConfig, EvalConfig, DriveConfig):
        hints = typing.get_type_hints(command)
        assert hints["scenario"] is Scenario and hints["where"] is Where, command
    for command in (ReplayConfig, ExperimentConfig, BridgeConfig):
        assert typing.get_type_hints(command)["where"] is Where, command
    assert not any(
        issubclass(command, (Scenario, Where))
        for command in (TrainConfig, EvalConfig, DriveConfig, ReplayConfig, ExperimentConfig)
    )


def test_the_densities_are_spelled_once():
    """The density words are written in the vocabulary alone; everything else reads them."""
    spelled = re.compile(r"""["']light["'],\s*["']medium["'],\s*["']heavy["']""")
    found = [
        str(path.relative_to(ROOT))
        for folder in ("protocol", "server", "client", "trainers", "viz")
        for path in sorted((ROOT / folder).rglob("*.py"))
        if spelled.search(path.read_text(encoding="utf-8"))
    ]
    assert found == ["protocol/vocabulary.py"]
    assert DENSITIES == ("light", "medium", "heavy")


def test_the_one_runner_drives_records_and_closes(tmp_path):
    """drive_episodes opens the simulator, asks for the driver with it, keeps the records
    numbered as the episodes, and closes the simulator even when the driver refuses."""
    opened, closed = [], []

    def open_envs():
        envs = Where().open("min2018", {"episode.max_decisions": 6, "camera.enabled": False}, 2)
        opened.append(envs)
        close = envs.close
        envs.close = lambda **kwargs: (closed.append(envs), close(**kwargs))
        return envs

    def keep(envs):
        assert envs.behaviour_spec.preset == "min2018"
        return Driver(lambda obs, info, starting: np.ones(2, dtype=np.int64), _source(), "up")

    driven = drive_episodes(
        Where(),
        "min2018",
        {"episode.max_decisions": 6},
        Episodes(seeds=(4, 9), labels=(7, 3)),
        keep,
        Keeping(records=True),
        open_envs=open_envs,
    )
    assert closed == opened
    assert [r.episode for r in driven.records] == [7, 3]
    assert [r.seed for r in driven.records] == [4, 9]
    assert all(r.actions == "1" * 6 for r in driven.records)
    assert [row["decisions"] for row in driven.rows] == [6.0, 6.0]
    path = driven.write_records(tmp_path)
    header, records = read_records(path)
    assert header.policy == _source() and header.name == "up" and len(records) == 2

    def refuse(envs):
        raise UsageError("not this one")

    with pytest.raises(UsageError, match="not this one"):
        drive_episodes(
            Where(), "min2018", {}, Episodes.from_seed(1, 0), refuse, open_envs=open_envs
        )
    assert len(opened) == 2 and closed == opened


def _source():
    from overtake.client.episodes.records import PolicySource

    return PolicySource("reference", "up")


def test_drive_takes_its_scenario_from_the_command_line_flags(tmp_path):
    out = tmp_path / "drive.json"
    drive(
        DriveConfig(
            policy="idle",
            episodes=2,
            json_out=out,
            scenario=Scenario(preset="ho2018", traffic="light", max_decisions=5),
        )
    )
    result = json.loads(out.read_text())
    assert result["preset"] == "ho2018"
    assert result["overrides"] == {"traffic.density": "light", "episode.max_decisions": 5}
    assert [row["decisions"] for row in result["episodes"]] == [5.0, 5.0]


def test_where_carries_every_remote_setting_into_the_connection(tmp_path):
    """Every setting of RemoteConfig is a flag of every command that takes --connect (its
    Where holds one) with the same name, and reaches the connection unchanged: nothing is
    dropped on the way, nothing is copied by hand."""
    import tyro

    from overtake.client.wire.remote_config import RemoteConfig
    from overtake.ipc.transport import SecurityConfig
    from overtake.trainers.experiment.plan import command_args

    asked = RemoteConfig(
        connect=("tcp/10.0.0.7:7447", "tcp/10.0.0.8:7447"),
        server="sim-2",
        connect_timeout_s=1.5,
        request_timeout_s=2.5,
        step_timeout_s=3.5,
        reconnect_timeout_s=4.5,
        lease_s=5.5,
        security=SecurityConfig(user="alice", tls_root_ca=tmp_path / "ca.pem", tls_mtls=True),
        trainer_name="alice",
        transport="zenoh",
        spin_s=0.0,
    )
    default = RemoteConfig()
    # Every setting is asked for here, so a new one this test does not carry fails it.
    unasked = [
        f.name
        for f in dataclasses.fields(RemoteConfig)
        if getattr(asked, f.name) == getattr(default, f.name)
    ]
    assert not unasked, f"give these a value other than the default: {unasked}"
    args = command_args(Where(connect=asked.connect, link=asked), Where())
    assert "--transport" in args and "--spin-s" in args
    parsed = tyro.cli(Where, args=args, config=(tyro.conf.OmitArgPrefixes,))
    assert parsed.remote() == asked
    # --connect is the command's own: none runs in process, and the RemoteConfig's is no flag.
    assert Where().in_process and not parsed.in_process
    with pytest.raises(SystemExit):
        tyro.cli(Where, args=["--link.connect", "tcp/x:1"], config=(tyro.conf.OmitArgPrefixes,))
    with pytest.raises(UsageError, match="no --connect"):
        Where().remote()
    # The defaults are RemoteConfig's own.
    on_default = Where(connect=asked.connect).remote()
    assert dataclasses.replace(on_default, connect=default.connect) == default

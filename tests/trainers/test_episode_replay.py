"""Episode records and their replay (issue 38): a kept episode plays again bit for bit, in
process and on a server, for every preset; a record that no longer describes this simulator, or
a replay that parts from its record, stops with a message naming what differs; a replayed
collision is in the recording at the decision the record names, its cars coloured."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from overtake.client.episodes.drive import DriveConfig
from overtake.client.episodes.drive import main as drive
from overtake.client.episodes.records import (
    EpisodeRecord,
    RecordError,
    read_header,
    read_records,
    write_records,
)
from overtake.client.episodes.scenario import Scenario, Where
from overtake.protocol import errors
from overtake.server.engine.requested import resolve_config
from overtake.server.sim import SimConfig, make_config
from overtake.server.sim.config import as_json
from overtake.server.sim.presets import PRESETS
from overtake.server.sim.settings_history import (
    as_recorded,
    undo_overrides,
    unexplained_differences,
)
from overtake.trainers.episode_replay import (
    ReplayConfig,
    ReplayDiverged,
    replay_envs,
)
from overtake.trainers.episode_replay import main as replay
from overtake.viz.recording import RecordingConfig

NO_RECORDING = RecordingConfig(sink="off")
# Short, crowded episodes where the car changes lanes as told (min2018's own check off): a
# random driver collides in some of them.
CROWDED = ("traffic.density=heavy", "ego.lane_change_check=false")
# The first seed of four such min2018 episodes one of which collides. (Since issue 68 the road
# starts empty and the authors' spawners fill it: about one of twelve collides, against one
# of three on the treadmill before, and none of the four from seed 3 does.)
CRASH_SEED = 5


def _drive(
    out: Path,
    preset: str,
    policy: str = "random",
    scene: tuple[str, ...] = CROWDED,
    seed: int = 3,
    **options,
) -> Path:
    drive(
        DriveConfig(
            policy=policy,  # type: ignore[arg-type]
            episodes=4,
            seed=seed,
            episodes_out=out,
            **options,
            scenario=Scenario(preset=preset, max_decisions=80, set=scene),
        )
    )
    [path] = list(out.glob("*.jsonl"))
    return path


def _rewrite(path: Path, edit_header=None, edit_episode=None) -> None:
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    if edit_header is not None:
        edit_header(lines[0])
    if edit_episode is not None:
        for line in lines[1:]:
            edit_episode(line)
    path.write_text("\n".join(json.dumps(line) for line in lines) + "\n")


def test_records_made_on_a_server_replay_in_process_and_on_the_server(tmp_path, start_server):
    # Every preset: kept on a server and in process, the same episodes (a server's simulator
    # is this one), and each replays in process to its record.
    server = start_server("episodes")
    for preset in sorted(PRESETS):
        remote = _drive(
            tmp_path / "remote" / preset, preset, where=Where(connect=(server.endpoint,))
        )
        local = _drive(tmp_path / "local" / preset, preset)
        header, episodes = read_records(remote)
        assert header.preset == preset and header.policy.kind == "reference"
        assert [e.seed for e in episodes] == [3, 4, 5, 6]
        for episode in episodes:
            assert len(episode.actions) == episode.metrics["decisions"]
            # The decisions where the counts rose are as many as the metrics count.
            for name in ("collisions", "emergency_brakes"):
                assert len(episode.events.get(name, ())) == episode.metrics[name]
        assert read_records(local)[1] == episodes
        assert replay(ReplayConfig(record=remote, recording=NO_RECORDING))["episodes"] == [
            0,
            1,
            2,
            3,
        ]
    replay(
        ReplayConfig(record=local, recording=NO_RECORDING, where=Where(connect=(server.endpoint,)))
    )
    # overtake-eval --record on a server: the car and its events (the road is the server's).
    rrd = tmp_path / "remote-eval.rrd"
    result = _evaluate_random(rrd, tmp_path / "remote-eval", connect=(server.endpoint,))
    _, episodes = read_records(Path(result["episodes_record"]))
    _assert_collisions_recorded(rrd, episodes)
    assert not _entities(rrd) & {"/world/episode/arena0/road/cars"}


def test_a_record_of_another_preset_or_other_overrides_is_refused(tmp_path):
    record = _drive(tmp_path / "records", "min2018", policy="rule")

    def other_preset(header):
        header["preset"] = "ho2018"

    _rewrite(record, edit_header=other_preset)
    with pytest.raises(RecordError, match=r"ho2018 .*resolves to another simulator") as refused:
        replay(ReplayConfig(record=record, recording=NO_RECORDING))
    assert "simulator than the record's: preset: 'min2018' in the record, 'ho2018' now" in str(
        refused.value
    )

    record = _drive(tmp_path / "again", "min2018", policy="rule")

    def other_overrides(header):
        header["overrides"]["traffic.density"] = "light"

    _rewrite(record, edit_header=other_overrides)
    with pytest.raises(RecordError, match="traffic.density: 'heavy' in the record, 'light' now"):
        replay(ReplayConfig(record=record, recording=NO_RECORDING))


def test_a_record_whose_checkpoint_is_gone_says_where_to_give_it(tmp_path):
    record = _drive(tmp_path / "records", "min2018", policy="rule")

    def moved(header):
        header["policy"] = {"kind": "checkpoint", "name": "runs/gone/checkpoint.pt", "step": 5}

    _rewrite(record, edit_header=moved)
    with pytest.raises(
        RecordError, match="checkpoint runs/gone/checkpoint.pt, which is not"
    ) as gone:
        replay(ReplayConfig(record=record, recording=NO_RECORDING))
    assert "--actions-only" in str(gone.value)
    # Without the driver the recorded actions still play, checked by each episode's metrics
    # and events; one changed action is caught there.
    rrd = tmp_path / "actions-only.rrd"
    replayed = replay(
        ReplayConfig(
            record=record, recording=RecordingConfig(sink="file", rrd=rrd), actions_only=True
        )
    )
    assert replayed["episodes"] == [0, 1, 2, 3]
    # No network is asked, so the layout has no (empty) Q-values plot; the rest is there.
    views = _view_names(rrd)
    assert {"rule: camera", "rule: speed (km/h)", "rule: action"} <= views
    assert not any(name.endswith("Q-values") for name in views)

    def changed(episode):
        if episode["episode"] == 2:
            flipped = "3" if episode["actions"][5] != "3" else "4"
            episode["actions"] = episode["actions"][:5] + flipped + episode["actions"][6:]

    _rewrite(record, edit_episode=changed)
    with pytest.raises(ReplayDiverged, match="episode 2"):
        replay(ReplayConfig(record=record, recording=NO_RECORDING, actions_only=True))


def test_a_replay_that_parts_from_its_record_says_where(tmp_path):
    # The rule driver decides on what it sees: a changed action makes the replayed car see
    # otherwise, and the replay names the first decision where the driver now disagrees.
    record = _drive(tmp_path / "rule", "min2018", policy="rule")
    _, episodes = read_records(record)
    changed = episodes[1]
    flipped = "0" if changed.actions[10] != "0" else "1"

    def edit(line):
        if line["episode"] == 1:
            line["actions"] = line["actions"][:10] + flipped + line["actions"][11:]

    _rewrite(record, edit_episode=edit)
    with pytest.raises(ReplayDiverged, match=r"episode 1 \(seed 4\) parts from its record at"):
        replay(ReplayConfig(record=record, recording=NO_RECORDING))
    # A random driver cannot be asked again: the metrics at the end tell the difference.
    record = _drive(tmp_path / "random", "min2018")

    def slower(line):
        if line["episode"] == 0:
            line["metrics"]["distance_m"] += 1.0

    _rewrite(record, edit_episode=slower)
    with pytest.raises(ReplayDiverged, match=r"episode 0 \(seed 3\) replayed with distance_m"):
        replay(ReplayConfig(record=record, recording=NO_RECORDING))


def test_episodes_are_chosen_by_number_or_by_collision(tmp_path, capsys):
    record = _drive(tmp_path / "records", "min2018", seed=CRASH_SEED)
    _, episodes = read_records(record)
    crashed = [e.episode for e in episodes if e.collisions]
    assert crashed, "heavy traffic and a random driver: some episode collides"
    assert (
        replay(ReplayConfig(record=record, collisions=True, recording=NO_RECORDING))["episodes"]
        == crashed
    )
    assert replay(ReplayConfig(record=record, episode=(2,), recording=NO_RECORDING))[
        "episodes"
    ] == [2]
    with pytest.raises(RecordError, match="has no episode 9: it holds episodes 0-3"):
        replay(ReplayConfig(record=record, episode=(9,), recording=NO_RECORDING))


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ('{"format": "something-else"}', "is not an episode record"),
        ('{"format": "overtake-episodes", "version": 99}', "version 99, this code reads"),
        ("not json", "line 1: not JSON"),
    ],
)
def test_a_file_that_is_not_a_record_is_refused_with_what_it_holds(tmp_path, line, message):
    path = tmp_path / "bad.jsonl"
    path.write_text(line + "\n")
    with pytest.raises(RecordError, match=message):
        read_records(path)
    with pytest.raises(RecordError, match=message):  # the header alone, checked the same
        read_header(path)


def test_an_episode_line_is_checked(tmp_path):
    record = _drive(tmp_path / "records", "min2018", policy="rule")
    header, episodes = read_records(record)
    bad = EpisodeRecord(0, 3, "01x", episodes[0].metrics)
    write_records(tmp_path / "letters.jsonl", header, [bad])
    with pytest.raises(RecordError, match=r"line 2: actions must be digits 0-4, got \['0', '1'"):
        read_records(tmp_path / "letters.jsonl")
    # The header alone is read without the episodes.
    assert read_header(tmp_path / "letters.jsonl") == header
    short = EpisodeRecord(0, 3, "01", episodes[0].metrics)
    write_records(tmp_path / "short.jsonl", header, [short])
    with pytest.raises(RecordError, match="2 actions for an episode of 80 decisions"):
        read_records(tmp_path / "short.jsonl")


def _text_events(rrd: Path) -> list[tuple[str, int, str]]:
    """(timeline, position, text) of every event logged to a recording."""
    import rerun as rr

    found = []
    for chunk in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path != "/episode/events":
            continue
        batch = chunk.to_record_batch()
        timelines = [f.name for f in batch.schema if f.name.startswith("episode ")]
        texts = [c for c in batch.schema.names if c.endswith("TextLog:text")]
        for row in range(batch.num_rows):
            for name in timelines:
                position = batch.column(name)[row].as_py()
                if position is not None:
                    text = batch.column(texts[0])[row].as_py()
                    found.append((name, position, text[0] if isinstance(text, list) else text))
    return found


def _car_colours(rrd: Path, timeline: str, position: int) -> np.ndarray:
    """The road view's box colours logged at ``position`` of ``timeline``."""
    import rerun as rr

    for chunk in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        if chunk.entity_path != "/world/episode/arena0/road/cars":
            continue
        batch = chunk.to_record_batch()
        if timeline not in batch.schema.names:
            continue
        colours = [c for c in batch.schema.names if c.endswith("Boxes2D:colors")]
        for row in range(batch.num_rows):
            if batch.column(timeline)[row].as_py() == position:
                return np.array(batch.column(colours[0])[row].as_py(), dtype=np.uint32)
    raise AssertionError(f"no road logged at {timeline} = {position}")


def test_a_replayed_collision_is_marked_at_its_decision_with_its_cars_coloured(tmp_path):
    from overtake.viz.world_view import EVENT_COLOUR

    record = _drive(tmp_path / "records", "min2018", seed=CRASH_SEED)
    _, episodes = read_records(record)
    crashed = [e for e in episodes if e.collisions]
    assert crashed
    rrd = tmp_path / "replay.rrd"
    replay(
        ReplayConfig(
            record=record, collisions=True, recording=RecordingConfig(sink="file", rrd=rrd)
        )
    )
    events = _text_events(rrd)
    packed = int.from_bytes(bytes([*EVENT_COLOUR, 255]), "big")
    for episode in crashed:
        [decision] = episode.events["collisions"]
        # A collision ends a min2018 episode: the metrics' last decision is the collision's.
        assert decision == episode.metrics["decisions"] - 1
        timeline = f"episode {episode.episode}"
        assert (timeline, decision, f"collision at decision {decision}") in {
            (name, position, text.split(",")[0]) for name, position, text in events
        }
        colours = _car_colours(rrd, timeline, decision)
        # The agent and the car it hit, and only at the collision.
        assert (colours == packed).sum() >= 2
        assert (_car_colours(rrd, timeline, decision - 1) == packed).sum() == 0
    assert not {name for name, _, _ in events} - {f"episode {e.episode}" for e in crashed}


class _OverriddenEveryFew:
    """Keeps its lane and speed, and says the shield overrode it at decisions 3, 10, 17, ..."""

    def __init__(self, n: int) -> None:
        self.n, self.calls = n, 0
        self.last_q: np.ndarray | None = None
        self.last_overridden: np.ndarray | None = None

    def __call__(self, obs, info, starting) -> np.ndarray:
        self.last_q = np.tile(np.arange(5.0), (self.n, 1))
        self.last_overridden = np.full(self.n, self.calls % 7 == 3)
        self.calls += 1
        return np.zeros(self.n, dtype=np.int64)


def test_the_shields_overrides_are_kept_and_recorded_at_their_decisions(tmp_path):
    from overtake.client.episodes.recording import open_episode_recording
    from overtake.client.episodes.records import EpisodeRecorder
    from overtake.client.episodes.runner import run_episodes
    from overtake.client.episodes.scenario import Where
    from overtake.viz.recording import close_recording

    envs = Where().open("min2018", {"episode.max_decisions": 30}, 2)
    policy = _OverriddenEveryFew(2)
    recorder = EpisodeRecorder([5, 6], policy)
    rrd = tmp_path / "shield.rrd"
    recording, view = open_episode_recording(
        RecordingConfig(sink="file", rrd=rrd), rrd, [0, 1], envs, policy, "test"
    )
    try:
        run_episodes(envs, policy, 2, 5, watchers=[recorder, view])
    finally:
        close_recording(recording)
        envs.close()
    for record in recorder.records():
        assert record.events["shield_overrides"] == (3, 10, 17, 24)
    overrides = [(n, p, t) for n, p, t in _text_events(rrd) if t.startswith("the shield")]
    assert sorted((n, p) for n, p, _ in overrides) == [
        (f"episode {e}", d) for e in (0, 1) for d in (3, 10, 17, 24)
    ]
    assert all(" with keep at decision " in t for _, _, t in overrides)


def _view_names(rrd: Path) -> set[str]:
    """Every text of the recording's layout (its views' names among them)."""
    import rerun as rr

    from tests.support.remote import blueprint_texts

    reader = rr.chunk.RrdReader(str(rrd))
    return set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))


def _entities(rrd: Path) -> set[str]:
    import rerun as rr

    return {c.entity_path for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks()}


def _assert_collisions_recorded(rrd: Path, episodes: list[EpisodeRecord]) -> None:
    """The recording's collision events are the record's, each at its decision."""
    logged = {
        (name, position)
        for name, position, text in _text_events(rrd)
        if text.startswith("collision at decision")
    }
    expected = {
        (f"episode {e.episode}", d) for e in episodes for d in e.events.get("collisions", ())
    }
    assert expected and logged == expected


def _evaluate_random(rrd: Path, records: Path, connect: tuple[str, ...] = ()) -> dict:
    """``overtake-eval --policy random`` over the crowded episodes, recorded and kept."""
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate

    return evaluate(
        EvalConfig(
            policy="random",
            episodes=4,
            seed=CRASH_SEED,
            record=rrd,
            episodes_out=records,
            scenario=Scenario(
                preset="min2018",
                traffic="heavy",
                set=("ego.lane_change_check=false",),
                max_decisions=80,
            ),
            where=Where(connect=connect),
        )
    )


def test_evaluation_records_its_episodes_as_it_drives_them(tmp_path):
    rrd = tmp_path / "eval.rrd"
    result = _evaluate_random(rrd, tmp_path / "records")
    header, episodes = read_records(Path(result["episodes_record"]))
    assert header.policy.kind == "reference" and header.policy.name == "random"
    assert [e.metrics for e in episodes] == [
        {k: v for k, v in row.items() if k != "shield_overrides"} for row in result["episodes"]
    ]
    _assert_collisions_recorded(rrd, episodes)
    assert {"/world/episode/arena0/road/cars", "/episode/car/camera"} <= _entities(rrd)


def test_a_replayed_emergency_brake_is_marked_with_its_cars(tmp_path):
    from overtake.viz.world_view import BRAKE_COLOUR

    # Light traffic that keeps its lanes (a car leaving the lane is no longer beside the agent
    # when the decision ends): the rule driver at 80 km/h comes upon cars that entered at 40-60.
    calm = (
        "traffic.density=light",
        "traffic.random.random_lane_change_rate_per_s=0",
        "traffic.random.lane_change_threshold_mps2=1000",
    )
    record = _drive(tmp_path / "records", "min2018", policy="rule", scene=calm)
    _, episodes = read_records(record)
    braked = [e for e in episodes if e.events.get("emergency_brakes")]
    assert braked, "the rule driver in light traffic brakes hard now and then"
    rrd = tmp_path / "brakes.rrd"
    replay(ReplayConfig(record=record, recording=RecordingConfig(sink="file", rrd=rrd)))
    events = {
        (name, position) for name, position, text in _text_events(rrd) if "emergency brake" in text
    }
    packed = int.from_bytes(bytes([*BRAKE_COLOUR, 255]), "big")
    for episode in braked:
        timeline = f"episode {episode.episode}"
        for decision in episode.events["emergency_brakes"]:
            assert (timeline, decision) in events
            # The braking car and the car it braked for.
            assert (_car_colours(rrd, timeline, decision) == packed).sum() == 2


def test_a_relative_checkpoint_name_is_found_within_the_records_experiment(tmp_path):
    """Kept records name their checkpoint within the experiment (no machine's directories):
    a replay finds it there, from wherever it runs."""
    from overtake.client.episodes.records import PolicySource, RecordHeader
    from overtake.trainers.episode_replay import _driver_file

    experiment = tmp_path / "experiment"
    record = experiment / "evaluations" / "a-seed0" / "medium.episodes" / "a.jsonl"
    record.parent.mkdir(parents=True)
    (experiment / "experiment.json").write_text("{}")
    checkpoint = experiment / "a-seed0" / "checkpoint.pt"
    checkpoint.parent.mkdir()
    checkpoint.write_bytes(b"")
    header = RecordHeader(
        "min2018", {}, {}, PolicySource("checkpoint", "a-seed0/checkpoint.pt", 5), "abc"
    )
    assert _driver_file(header, ReplayConfig(record=record)) == checkpoint
    checkpoint.unlink()
    with pytest.raises(RecordError, match="a-seed0/checkpoint.pt, which is not there"):
        _driver_file(header, ReplayConfig(record=record))


KEPT = Path(__file__).resolve().parents[2] / "bench" / "results"


def _kept_record_per_commit_and_preset() -> list[Path]:
    """One record of each (commit, preset) the experiments kept in bench/results."""
    chosen: dict[tuple[str, str], Path] = {}
    for path in sorted(KEPT.rglob("*.jsonl")):
        header = read_header(path)
        chosen.setdefault((header.commit, header.preset), path)
    return list(chosen.values())


@pytest.mark.parametrize(
    "record", _kept_record_per_commit_and_preset(), ids=lambda p: str(p.relative_to(KEPT))
)
def test_every_kept_record_replays_on_the_simulator_it_was_made_on(record):
    # The kept tables' replay commands work from today's code: a setting added or changed
    # since the record was made is in the simulator's settings' history
    # (overtake.server.sim.settings_history), else the replay refuses the record.
    header = read_header(record)
    replay_envs(header, 1).close()


def _as_recorded(config: SimConfig) -> dict:
    """A configuration as a record's header holds it (JSON)."""
    return as_json(config)


def test_a_setting_added_since_a_record_is_set_to_what_it_was_before_it_existed():
    recorded = _as_recorded(make_config("min2018"))
    now = _as_recorded(make_config("min2018", {"ego.lane_change_watch": True}))
    for name in ("lane_change_watch", "watch_brake_mps2", "watch_response_s"):
        del recorded["ego"][name]
    assert undo_overrides(recorded, now) == {"ego.lane_change_watch": False}
    assert unexplained_differences(recorded, now) == []
    # A setting the history does not name as added is a difference the replay reports.
    del recorded["ego"]["length_m"]
    assert unexplained_differences(recorded, now) == [
        f"ego.length_m: absent from the record, {now['ego']['length_m']!r} now"
    ]


SPAWNER_SETTINGS = (
    "spawner_count",
    "spawner_step_s",
    "spawner_wait_s",
    "spawner_ahead_share",
    "spawner_clearance_m",
    "spawner_clearance_lanes",
)


def test_a_min2018_record_of_before_the_spawners_replays_on_the_treadmill(tmp_path):
    """Issue 68 gave min2018 its authors' spawners; a record made before holds the treadmill
    (traffic.entry "comfortable") and none of the spawners' settings, and replays on the
    treadmill bit for bit (the replay checks every episode's metrics and events)."""
    treadmill = (*CROWDED, "traffic.entry=comfortable")
    record = _drive(tmp_path / "records", "min2018", policy="rule", scene=treadmill)

    def as_before_68(header):
        del header["overrides"]["traffic.entry"]
        for name in SPAWNER_SETTINGS:
            del header["config"]["traffic"][name]

    _rewrite(record, edit_header=as_before_68)
    header = read_header(record)
    assert "traffic.entry" not in header.overrides
    built = as_recorded("min2018", header.overrides, header.config)
    assert built.traffic.entry == "comfortable"
    assert make_config("min2018", header.overrides).traffic.entry == "spawners"
    assert replay(ReplayConfig(record=record, recording=NO_RECORDING))["episodes"] == [0, 1, 2, 3]
    # Before issue 44 a record held no traffic.entry at all: the treadmill, too.
    del header.config["traffic"]["entry"]
    assert as_recorded("min2018", header.overrides, header.config).traffic.entry == "comfortable"


def test_the_server_builds_a_records_simulator_or_refuses_naming_the_difference():
    """What a trainer sends (OpenRequest.as_recorded, the record's configuration as JSON) is
    built by the server from its own history: no client knows the simulator's settings."""
    recorded = _as_recorded(make_config("min2018"))
    for name in ("lane_change_watch", "watch_brake_mps2", "watch_response_s"):
        del recorded["ego"][name]
    built = resolve_config("min2018", {}, json.dumps(recorded))
    assert built == as_recorded("min2018", {}, recorded)
    assert built.ego.lane_change_watch is False  # what it was before the setting existed
    recorded["ego"]["length_m"] = 9.0
    with pytest.raises(errors.BadConfig, match=r"ego\.length_m: 9\.0 in the record, 4\.\d+ now"):
        resolve_config("min2018", {}, json.dumps(recorded))
    with pytest.raises(errors.BadConfig, match="as_recorded is not JSON"):
        resolve_config("min2018", {}, "{not json")
    with pytest.raises(errors.BadConfig, match=r"a JSON object\), got list"):
        resolve_config("min2018", {}, "[1, 2]")


def test_a_what_if_change_is_put_in_the_record_and_the_rest_still_checked(tmp_path):
    record = _drive(tmp_path / "records", "min2018", policy="rule")
    header = read_header(record)
    envs = replay_envs(header, 1, changes={"ego.lane_change_watch": True})
    try:
        assert envs.sim_config["ego"]["lane_change_watch"] is True
    finally:
        envs.close()

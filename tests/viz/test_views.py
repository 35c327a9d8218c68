"""What a researcher sees in Rerun: joined recordings under one layout, and what the viewer
itself draws of a road (a recording rendered by Rerun's own viewer, read back as pixels)."""

from __future__ import annotations

import io
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from overtake.protocol.messages import WorldFrame
from overtake.trainers.run.visual import TrainingRecording
from overtake.viz.layout import LayoutConfig, LayoutError, read_contents
from overtake.viz.layout import main as join
from overtake.viz.recording import APPLICATION_ID, RecordingConfig, open_recording
from overtake.viz.world_view import KIND_COLOURS, WorldRecording

from tests.support.remote import blueprint_texts, remote_config, strings_in, wait_until

AGENT_X_M = 1000.0
# Traffic around the agent (x ahead of it in metres, lane): far enough apart to tell apart
# in a picture, every one in the road view's window.
TRAFFIC = ((-30.0, 0), (-12.0, 2), (15.0, 4), (30.0, 1), (48.0, 3), (66.0, 0))


def road_frame(round_: int, arena: int = 3, step: int = -1) -> WorldFrame:
    """One agent in the middle lane of 5 and the :data:`TRAFFIC` cars, all steady drivers."""
    lane_width = 3.5
    x = np.array([AGENT_X_M + round_] + [AGENT_X_M + round_ + dx for dx, _ in TRAFFIC])
    y = (np.array([2] + [lane for _, lane in TRAFFIC]) + 0.5) * lane_width
    count = x.size
    return WorldFrame(
        server="s",
        group=0,
        arena=arena,
        round=round_,
        sim_time_s=0.4 * round_,
        lane_count=5,
        lane_width_m=lane_width,
        agent_kind=4,
        agent_active=np.ones(1, bool),
        x_m=x,
        y_m=y,
        speed_mps=np.full(count, 20.0, np.float32),
        kind=np.array([4] + [0] * len(TRAFFIC), np.int8),
        active=np.ones(count, bool),
        observations={"lidar": np.full((1, 36), 80.0, np.float32)},
        reward=np.ones(1),
        action_applied=np.array([round_ % 5]),
        reward_terms=np.array([[0.5, -0.25]]),
        reward_term_names=("speed", "lane_change"),
        trainer_step=step,
        half_length_m=np.full(count, 2.25, np.float32),
        half_width_m=np.full(count, 0.9, np.float32),
        agent_heading_rad=np.zeros(1, np.float32),
    )


def record_world(path, frames) -> None:
    recording = open_recording(
        APPLICATION_ID, RecordingConfig(rrd=path, recording_id="joined"), path
    )
    view = WorldRecording(recording.stream, rays=False)
    for frame in frames:
        view.log(frame)
    recording.close()


def record_run(path, run: str, arena: int, algo_index: int) -> None:
    recording = open_recording(
        APPLICATION_ID, RecordingConfig(rrd=path, recording_id="joined"), path
    )
    view = TrainingRecording(recording.stream, run, colour_index=algo_index)
    view.arenas("s", [arena])
    for step in range(0, 400, 100):
        view.episode(step, {"return": step / 10, "avg_speed_kmh": 60.0, "collisions": 0.0})
        view.learning(step, {"loss": 1.0 / (step + 1), "epsilon": 1.0 - step / 400})
        view.car_view(
            step, {"lidar": np.full(36, 40.0, np.float32)}, 1, np.arange(5.0), 0.5, {"speed": 0.5}
        )
    recording.close()


def test_layout_joins_a_spectator_and_two_trainers_into_one_laid_out_recording(tmp_path):
    record_world(tmp_path / "world.rrd", [road_frame(r, 3, 10 * r) for r in range(5)])
    record_world(tmp_path / "world2.rrd", [road_frame(r, 4, 10 * r) for r in range(5)])
    record_run(tmp_path / "dqn.rrd", "dqn", 3, 0)
    record_run(tmp_path / "dueling.rrd", "dueling", 4, 2)
    inputs = [tmp_path / f"{name}.rrd" for name in ("world", "world2", "dqn", "dueling")]

    contents = read_contents(inputs)
    assert contents.runs == ["dqn", "dueling"]
    assert [(s.server, s.arena, s.lane_count) for s in contents.shapes] == [
        ("s", 3, 5),
        ("s", 4, 5),
    ]
    assert contents.run_arenas == {"dqn": ("s", [3]), "dueling": ("s", [4])}

    out = tmp_path / "joined.rrd"
    join(LayoutConfig(recordings=tuple(inputs), out=out))
    reader = rr.chunk.RrdReader(str(out))
    # One recording with everything the four files held, and one layout: the processes' own
    # layouts stay behind (the viewer would show whichever came last).
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    joined = {c.entity_path for c in reader.stream().to_chunks()}
    for path in inputs:
        assert {c.entity_path for c in rr.chunk.RrdReader(str(path)).stream().to_chunks()} <= joined
    texts = blueprint_texts(reader, reader.blueprints()[0])
    # Each run's road beside the curves where every run is a line, then the rest.
    assert {
        "compare",
        "dqn: road (arena 3, agent 0 at 0 m)",
        "dueling: road (arena 4, agent 0 at 0 m)",
        "/world/s/arena3/road",
        "/world/s/arena4/road",
        "episode return",
        "/training/episode/return/**",
        "cars",
        "/trainer/dqn/env0/camera",
        "s arena 3 (dqn)",
        "s arena 4 (dueling)",
        "step",
    } <= texts
    assert not (tmp_path / "joined.rrd.partial").exists()


def test_layout_says_what_is_wrong_with_its_input(tmp_path):
    with pytest.raises(LayoutError, match="no such recording: .*missing.rrd"):
        join(LayoutConfig(recordings=(tmp_path / "missing.rrd",), out=tmp_path / "o.rrd"))
    (tmp_path / "junk.rrd").write_bytes(b"not a recording")
    with pytest.raises(LayoutError, match="cannot read the recording .*junk.rrd"):
        join(LayoutConfig(recordings=(tmp_path / "junk.rrd",), out=tmp_path / "o.rrd"))
    empty = tmp_path / "empty.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=empty), empty)
    recording.stream.log("something/else", rr.Scalars(1.0))
    recording.close()
    with pytest.raises(LayoutError, match="neither training runs nor roads"):
        join(LayoutConfig(recordings=(empty,), out=tmp_path / "o.rrd"))
    assert not (tmp_path / "o.rrd").exists()


def colour_runs(image: np.ndarray, colour: np.ndarray, tolerance: int = 40) -> int:
    """How many separate runs of columns hold pixels of ``colour``: boxes apart along x."""
    close = (np.abs(image[..., :3].astype(int) - colour.astype(int)) <= tolerance).all(axis=-1)
    columns = np.flatnonzero(close.any(axis=0))
    if columns.size == 0:
        return 0
    return int(1 + np.count_nonzero(np.diff(columns) > 3))


needs_viewer = pytest.mark.skipif(
    shutil.which("xvfb-run") is None,
    reason="drawing with Rerun's viewer headless needs xvfb-run and Mesa's software Vulkan "
    "(apt-get install xvfb mesa-vulkan-drivers; scripts/setup-viewer.sh)",
)


@needs_viewer
@pytest.mark.timeout(180)
def test_the_viewer_draws_every_car_of_the_road(tmp_path):
    """The test that would have caught invisible traffic: the picture Rerun's own viewer draws
    of the road holds a box for every car, not only the agent's."""
    from PIL import Image

    from overtake.viz.render import RenderConfig
    from overtake.viz.render import main as render

    def viewer_leftovers() -> set[str]:
        # What the viewer and xvfb-run, ended by a signal, used to leave in the temp folder.
        return {
            p.name
            for pattern in ("rerun-data-*", "xvfb-run.*", "overtake-viewer-*")
            for p in Path(tempfile.gettempdir()).glob(pattern)
        }

    before = viewer_leftovers()
    rrd = tmp_path / "road.rrd"
    record_world(rrd, [road_frame(0)])
    (picture,) = render(
        RenderConfig(
            recordings=(rrd,),
            out=tmp_path / "road.png",
            views=("arena 3: road (agent 0 at 0 m, left up)",),
            width=1400,
            height=900,
        )
    )
    image = np.asarray(Image.open(io.BytesIO(picture.read_bytes())).convert("RGB"))
    steady = KIND_COLOURS[0]
    assert colour_runs(image, steady) == len(TRAFFIC)
    assert colour_runs(image, np.array([230, 40, 40])) >= 1  # the agent
    assert viewer_leftovers() <= before


def test_a_road_recording_shared_with_trainers_lays_out_their_plots_too(tmp_path):
    """Live, the viewer shows the last layout it received: a spectator's or server's that
    shares the trainers' recording id must show their plots as well as the roads."""
    rrd = tmp_path / "world.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=rrd, recording_id="shared"), rrd)
    view = WorldRecording(recording.stream, rays=False, with_training=True)
    for round_ in range(3):
        view.log(road_frame(round_, 3, 100 * round_))
    recording.close()
    reader = rr.chunk.RrdReader(str(rrd))
    texts = set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))
    assert {
        "compare",
        "s arena 3",
        "/world/s/arena3/road",
        "episode return",
        "/training/episode/return/**",
        "training: every run",
        "step",
    } <= texts
    alone = tmp_path / "alone.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=alone), alone)
    view = WorldRecording(recording.stream, rays=False)
    view.log(road_frame(0, 3, 0))
    recording.close()
    reader = rr.chunk.RrdReader(str(alone))
    texts = set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))
    assert "/world/s/arena3/road" in texts and "/training/episode/return/**" not in texts


@needs_viewer
@pytest.mark.timeout(180)
def test_a_live_viewer_shows_one_layout_for_a_spectator_and_a_trainer(start_server, tmp_path):
    """Streamed live (``--sink grpc``) by a trainer and a spectator sharing a recording id,
    Rerun's viewer holds one recording and shows one layout: the roads and the trainer's
    plots, not the layout the viewer would make up, nor the trainer's alone."""
    import threading
    import time

    import gymnasium as gym

    import overtake.client  # noqa: F401  (registers the environments)
    from overtake.client.wire.spectate import SpectateConfig
    from overtake.client.wire.spectate import main as spectate
    from overtake.envs import REMOTE_HIGHWAY_ENV_ID
    from overtake.viz.recording import close_recording
    from overtake.viz.render import headless_viewer
    from overtake.viz.training_layout import training_blueprint

    server = start_server("live", world_rate_hz=50)
    with headless_viewer(1200, 800) as (client, _):
        streamed = RecordingConfig(sink="grpc", viewer_url=str(client.url), recording_id="live")
        # The trainer first, as overtake-train does: its own layout goes with its stream.
        trainer = open_recording(
            APPLICATION_ID, streamed, tmp_path / "unused.rrd", training_blueprint("dqn")
        )
        view = TrainingRecording(trainer.stream, "dqn")
        env = gym.make(REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name))
        watcher = threading.Thread(
            target=spectate,
            args=(
                SpectateConfig(
                    connect=(server.endpoint,),
                    server=server.name,
                    frames=10,
                    seconds=60,
                    recording=streamed,
                ),
            ),
        )
        try:
            env.reset(seed=1)
            watcher.start()
            deadline = time.monotonic() + 60
            step = 0
            while watcher.is_alive() and time.monotonic() < deadline:
                env.unwrapped.label_step(step)
                env.step(1)
                view.episode(step, {"return": float(step)})
                step += 1
            watcher.join(timeout=30)
        finally:
            env.close()
            close_recording(trainer)
        arena = env.unwrapped.group.arena_ids[0]

        def layout() -> set[str]:
            return strings_in(client.get_blueprint().blueprint)

        wait_until(lambda: "compare" in layout(), 30, "the joined layout in the viewer")
        shown = layout()
        assert {f"/world/live/arena{arena}/road", "/training/episode/return/**"} <= shown
        assert len(client.get_state().recordings) == 1  # one recording, not two


def test_layout_names_the_file_whose_arena_shape_it_cannot_read(tmp_path):
    bad = tmp_path / "bad.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=bad), bad)
    recording.stream.log("world/s/arena3/shape", rr.AnyValues(server=["s"]), static=True)
    recording.close()
    with pytest.raises(
        LayoutError, match=r"bad.rrd: /world/s/arena3/shape is not an arena's shape"
    ):
        read_contents([bad])


@needs_viewer
@pytest.mark.slow  # Rerun's viewer once a tab (11 s); one draw: the test above
@pytest.mark.timeout(240)
def test_a_tab_pattern_draws_every_tab_it_names_each_to_its_own_file(tmp_path):
    """``overtake-render --tabs "*"`` wrote ``render-.png`` once (the pattern's own empty
    name); now each tab the pattern names is drawn to a file named by its title."""
    from overtake.viz.render import RenderConfig
    from overtake.viz.render import main as render

    rrd = tmp_path / "world.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=rrd, recording_id="tabs"), rrd)
    view = WorldRecording(recording.stream, rays=False, with_training=True)
    for round_ in range(3):
        view.log(road_frame(round_, 3, 100 * round_))
    recording.close()
    # What is checked is which files are written, not what the notifications cover.
    written = render(
        RenderConfig(recordings=(rrd,), out=tmp_path / "demo.png", tabs=("*",), notifications_s=0.0)
    )
    names = [path.name for path in written]
    assert len(names) >= 2 and len(set(names)) == len(names), names
    assert "demo-.png" not in names and "demo-compare.png" in names
    assert all(path.is_file() and path.stat().st_size > 1000 for path in written)


@needs_viewer
@pytest.mark.timeout(120)
def test_extra_arguments_reach_the_viewer(tmp_path):
    """``--extra-args`` go on the viewer's command line (they were accepted and dropped): one it
    does not know ends it, and the error says what the viewer said."""
    from overtake.viz.render import RenderConfig, RenderError
    from overtake.viz.render import main as render

    rrd = tmp_path / "road.rrd"
    record_world(rrd, [road_frame(0)])
    config = RenderConfig(recordings=(rrd,), out=tmp_path / "road.png", extra_args=("--no-such",))
    with pytest.raises(RenderError, match="the viewer exited with code .*--no-such"):
        render(config)
    assert not config.out.exists()


def test_highway_scenes_name_their_actions_as_highway_env_does(tmp_path):
    """The presets highway-fast and highway say highway-env's names of the five actions in
    their behaviour spec (in overtake's order), and a training recording's car plots them so."""
    from overtake.envs.highway_env_like import ACTION_LABELS, TO_OVERTAKE
    from overtake.protocol.vocabulary import ACTION_NAMES, HIGHWAY_ENV_ACTION_NAMES
    from overtake.server.engine.env import HighwayEnv

    names = {}
    for preset in ("highway-fast", "highway", "min2018"):
        env = HighwayEnv(preset=preset, overrides={"camera.enabled": False})
        names[preset] = env.behaviour_spec.action_names
        env.close()
    assert names["highway-fast"] == names["highway"] == HIGHWAY_ENV_ACTION_NAMES
    assert names["min2018"] == ACTION_NAMES
    for highway_env_number, label in enumerate(ACTION_LABELS):  # the same action, both ways
        assert HIGHWAY_ENV_ACTION_NAMES[TO_OVERTAKE[highway_env_number]] == label

    path = tmp_path / "run.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=path), path)
    view = TrainingRecording(recording.stream, "run", action_names=names["highway-fast"])
    view.car_view(0, {}, 4, np.arange(5.0), 0.5, {})
    recording.close()
    paths = {chunk.entity_path for chunk in rr.chunk.RrdReader(path).stream().to_chunks()}
    car = "/trainer/run/env0"
    assert {f"{car}/q/{name}" for name in HIGHWAY_ENV_ACTION_NAMES} <= paths
    assert {f"{car}/action/{name}" for name in HIGHWAY_ENV_ACTION_NAMES} <= paths
    assert not any(old in p for p in paths for old in ACTION_NAMES)
    with pytest.raises(ValueError, match="expected 5 action names"):
        TrainingRecording(recording.stream, "run", action_names=("IDLE", "FASTER"))

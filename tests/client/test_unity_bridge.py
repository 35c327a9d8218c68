"""overtake-unity-bridge with ML-Agents' own Python side as the real client: mlagents-envs
1.1.0's ``UnityEnvironment`` and ``UnityToGymWrapper`` (in .venv-mlagents, protobuf 3.20:
tests/client/mlagents_side.py) listen, the bridge (this environment) dials them and serves
arenas of a real overtake server. Where mlagents-envs or .venv-mlagents is missing these tests skip,
saying so (scripts/setup-mlagents.sh installs both)."""

from __future__ import annotations

import io
import json
import signal
import socket
import struct
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from overtake.client.episodes.scenario import parse_overrides
from overtake.client.mlagents.unity_bridge import (
    COMPRESSION_NONE,
    COMPRESSION_PNG,
    ENVIRONMENT_PARAMETERS_CHANNEL,
    BridgeError,
    agent_infos,
    compatible,
    environment_parameter,
    load_messages,
    observation_proto,
    override_value,
    side_channel_messages,
)
from overtake.client.mlagents.wrappers import MLAgentsMissing
from overtake.protocol.messages import Steps

from tests.support.remote import child_env, free_port, stop_process, wait_until

ROOT = Path(__file__).resolve().parents[2]
ML_PYTHON = ROOT / ".venv-mlagents" / "bin" / "python"
ML_SIDE = Path(__file__).resolve().parent / "mlagents_side.py"
# Episodes of 12 decisions on a road of 10 cars, which random driving here lives through: every
# episode ends at the time limit.
SHORT = ("episode.max_decisions=12", "traffic.vehicle_count=10")

try:
    MESSAGES = load_messages()
except MLAgentsMissing as missing:
    pytest.skip(f"no ML-Agents message definitions: {missing}", allow_module_level=True)


def ml_side_problem() -> str | None:
    """Why ML-Agents' side cannot run here (None: it can)."""
    if not ML_PYTHON.exists():
        return "ML-Agents' side needs .venv-mlagents (scripts/setup-mlagents.sh creates it)"
    probe = subprocess.run(
        [str(ML_PYTHON), "-c", "import mlagents_envs.environment"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or [f"exit status {probe.returncode}"])[-1]
        return (
            f"mlagents-envs does not import in .venv-mlagents (scripts/setup-mlagents.sh): {last}"
        )
    return None


ML_SIDE_PROBLEM = ml_side_problem()
needs_ml_side = pytest.mark.skipif(ML_SIDE_PROBLEM is not None, reason=str(ML_SIDE_PROBLEM))


# --- the pieces ----------------------------------------------------------------------------------


def test_versions_follow_ml_agents_compatibility_rule():
    assert compatible("1.5.0", "1.5.0") and compatible("1.5.0", "1.0.0")
    assert not compatible("1.5.0", "2.0.0") and not compatible("1.5.0", "0.15.0")
    assert compatible("0.15.0", "0.15.1") and not compatible("0.15.0", "0.16.0")
    assert not compatible("1.5.0", "garbage") and not compatible("1.5.0", "")


def frame(channel: uuid.UUID, payload: bytes) -> bytes:
    """One side-channel frame as ML-Agents' SideChannelManager writes it (written out here)."""
    return channel.bytes_le + struct.pack("<i", len(payload)) + payload


def float_parameter(key: str, value: float) -> bytes:
    """EnvironmentParametersChannel.set_float_parameter's payload (written out here)."""
    encoded = key.encode("ascii")
    return struct.pack("<i", len(encoded)) + encoded + struct.pack("<if", 0, value)


def test_the_bridge_refuses_to_start_without_a_server_to_open_arenas_on():
    """Its Where may name no endpoint (it is every command's); the bridge needs one, and says
    so before it dials ML-Agents."""
    from overtake.client.mlagents.unity_bridge import BridgeConfig, main

    with pytest.raises(BridgeError, match="--connect is required"):
        main(BridgeConfig())


def test_side_channel_frames_and_environment_parameters_are_read():
    other = uuid.UUID("e951342c-4f7e-11ea-b238-784f4387d1f7")
    data = frame(other, b"\x01\x02") + frame(
        ENVIRONMENT_PARAMETERS_CHANNEL, float_parameter("traffic.vehicle_count", 25.0)
    )
    messages = side_channel_messages(data)
    assert [c for c, _ in messages] == [other, ENVIRONMENT_PARAMETERS_CHANNEL]
    assert environment_parameter(messages[1][1]) == ("traffic.vehicle_count", 25.0)
    assert override_value(25.0) == 25 and isinstance(override_value(25.0), int)
    assert override_value(0.5) == 0.5
    sampler = struct.pack("<i", 1) + b"k" + struct.pack("<i", 1) + b"\x00" * 12
    assert environment_parameter(sampler) is None
    with pytest.raises(BridgeError, match="cut short at byte 0 of 10"):
        side_channel_messages(data[:10])
    with pytest.raises(BridgeError, match="says 99 bytes, 2 left"):
        side_channel_messages(other.bytes_le + struct.pack("<i", 99) + b"ab")


def test_observations_take_ml_agents_layout_camera_pixels_as_png():
    from PIL import Image

    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (8, 6), dtype=np.uint8)
    obs = observation_proto(MESSAGES, "camera", grey)
    assert obs.compression_type == COMPRESSION_PNG and list(obs.shape) == [1, 8, 6]
    assert list(obs.dimension_properties) == [1, 2, 2]  # NONE, TE, TE: channels first
    decoded = np.array(Image.open(io.BytesIO(obs.compressed_data)))
    assert decoded.shape == (8, 6, 3) and all((decoded[..., c] == grey).all() for c in range(3))
    rgb = rng.integers(0, 256, (8, 6, 3), dtype=np.uint8)
    obs = observation_proto(MESSAGES, "camera", rgb)
    assert list(obs.shape) == [3, 8, 6]
    assert np.array_equal(np.array(Image.open(io.BytesIO(obs.compressed_data))), rgb)
    grid = rng.integers(-1, 2, (36, 3)).astype(np.int8)
    obs = observation_proto(MESSAGES, "grid", grid)
    assert obs.compression_type == COMPRESSION_NONE and list(obs.shape) == [1, 36, 3]
    assert np.array_equal(np.array(obs.float_data.data).reshape(36, 3), grid)
    lidar = rng.uniform(0, 80, 360).astype(np.float32)
    obs = observation_proto(MESSAGES, "lidar", lidar)
    assert list(obs.shape) == [360] and list(obs.dimension_properties) == [1]
    assert np.array_equal(np.array(obs.float_data.data, dtype=np.float32), lidar)
    with pytest.raises(BridgeError, match=r"shape \(2, 3, 4\)"):
        observation_proto(MESSAGES, "odd", np.zeros((2, 3, 4), np.float32))


def test_agent_infos_put_ended_agents_first_and_invert_the_masks():
    steps = Steps.trusted(
        server="s",
        group=1,
        round=3,
        agents=np.array([0, 1, 2], dtype=np.int32),
        observations={"ego": np.arange(6, dtype=np.float32).reshape(3, 2)},
        reward=np.array([0.5, -1.0, 2.0]),
        terminated=np.array([False, True, False]),
        truncated=np.array([False, False, False]),
        action_applied=np.zeros(3, np.int64),
        late=np.zeros(3, bool),
        action_mask=np.array([[1, 1, 0, 1, 1], [1, 1, 1, 1, 1], [0, 1, 1, 1, 1]], np.int8),
        reward_terms=np.zeros((3, 1)),
        metrics=np.zeros((3, 1)),
    )
    infos, deciding = agent_infos(steps, MESSAGES)
    assert [i.id for i in infos] == [1, 0, 2] and deciding == [0, 2]
    assert [i.done for i in infos] == [True, False, False]
    assert not infos[0].max_step_reached and len(infos[0].action_mask) == 0
    assert list(infos[1].action_mask) == [False, False, True, False, False]
    assert list(infos[2].action_mask) == [True, False, False, False, False]
    assert [i.reward for i in infos] == [-1.0, 0.5, 2.0]
    assert list(infos[2].observations[0].float_data.data) == [4.0, 5.0]


# --- ML-Agents' own client ------------------------------------------------------------------------


class Pair:
    """ML-Agents' side (tests/client/mlagents_side.py in .venv-mlagents) listening on a free
    port, and the bridge dialling it; both ended by PID at teardown."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.port = free_port()
        self.ml: subprocess.Popen | None = None
        self.bridge: subprocess.Popen | None = None
        self.bridge_log = tmp_path / f"bridge-{self.port}.log"

    def start_ml(self, scenario: str, steps: int = 0) -> subprocess.Popen:
        with open(self.tmp_path / "ml.log", "wb") as log:  # the child keeps its own handle
            self.ml = subprocess.Popen(
                [str(ML_PYTHON), str(ML_SIDE), scenario, str(self.port), str(steps)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
            )

        def listening() -> bool:
            assert self.ml is not None
            if self.ml.poll() is not None:
                raise AssertionError(f"ML-Agents' side exited: {self.ml_log()}")
            with socket.socket() as probe:
                return probe.connect_ex(("127.0.0.1", self.port)) == 0

        wait_until(listening, timeout_s=30, what="ML-Agents' gRPC server listening")
        return self.ml

    def start_bridge(self, endpoint: str, *args: str) -> subprocess.Popen:
        with open(self.bridge_log, "wb") as log:  # the child keeps its own handle
            self.bridge = self._start_bridge(log, endpoint, *args)
        return self.bridge

    def _start_bridge(self, log: Any, endpoint: str, *args: str) -> subprocess.Popen:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "overtake.client.mlagents.unity_bridge",
                "--connect",
                endpoint,
                "--port",
                str(self.port),
                "--host",
                "127.0.0.1",
                *args,
            ],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=child_env(),
            cwd=ROOT,
        )

    def ml_result(self, timeout_s: float = 120) -> dict:
        assert self.ml is not None and self.ml.stdout is not None
        out, _ = self.ml.communicate(timeout=timeout_s)
        lines = [line for line in out.splitlines() if line.startswith("{")]
        assert lines, f"ML-Agents' side printed nothing; its log: {self.ml_log()}"
        return json.loads(lines[-1])

    def bridge_exit(self, timeout_s: float = 60) -> tuple[int, str]:
        assert self.bridge is not None
        code = self.bridge.wait(timeout=timeout_s)
        return code, self.bridge_log.read_text()

    def ml_log(self) -> str:
        path = self.tmp_path / "ml.log"
        return path.read_text()[-3000:] if path.exists() else ""

    def stop(self) -> None:
        for proc in (self.bridge, self.ml):
            if proc is not None and proc.poll() is None:
                stop_process(proc)


@pytest.fixture
def pair(tmp_path):
    started = Pair(tmp_path)
    yield started
    started.stop()


def wait_arenas_freed(server, timeout_s: float) -> None:
    wait_until(
        lambda: server.probe().discover()[0].arenas_used == 0,
        timeout_s=timeout_s,
        what=f"server {server.name}'s arenas freed",
    )


def in_process_first_observations(arenas: int, seed: int) -> dict[str, np.ndarray]:
    """Agent 0's first observation after a reset with ``seed``, in this process."""
    import overtake.client  # noqa: F401  (registers the environments)

    env = gym.make_vec(
        "overtake/Highway-v0",
        num_envs=arenas,
        vectorization_mode="vector_entry_point",
        preset="min2018",
        overrides=parse_overrides(SHORT),
    )
    obs, _ = env.reset(seed=seed)
    env.close()
    return {name: values[0] for name, values in obs.items()}


@needs_ml_side
def test_unity_environment_steps_resets_and_sets_parameters_through_the_bridge(pair, shared_server):
    server = shared_server
    pair.start_ml("steps", 40)
    pair.start_bridge(server.endpoint, "--arenas", "2", "--set", *SHORT)
    result = pair.ml_result()
    assert "error" not in result, result
    code, log = pair.bridge_exit()
    assert code == 0, log
    assert "the ML-Agents process closed the environment" in log
    assert result["behaviors"] == ["min2018?team=0"]
    assert result["observations"] == [
        ["lidar", [360], [1]],
        ["camera", [1, 80, 80], [1, 2, 2]],
        ["ego", [6], [1]],
    ]
    assert result["branches"] == [5] and result["continuous"] == 0
    assert result["agents_at_reset"] == [0, 1]
    # What ML-Agents received is the simulation's own first observation for the seed it
    # gave (7: arenas 7 and 8), camera pixels scaled to [0, 1] as Unity's are.
    local = in_process_first_observations(2, 7)
    first = result["first"]
    assert np.array_equal(np.array(first["lidar"], np.float32), local["lidar"])
    assert np.array_equal(np.array(first["ego"], np.float32), local["ego"])
    np.testing.assert_allclose(first["camera"], local["camera"].ravel() / 255.0, atol=1e-6)
    # 40 decisions with 12-decision episodes: every agent ended at the time limit.
    assert sorted(set(result["terminal_ids"])) == [0, 1]
    assert all(result["interrupted"]) and result["masks_ok"]
    assert result["first_after_second_reset"]["lidar"] != first["lidar"]  # new seeds
    assert result["agents_after_parameters"] == 2
    assert "environment parameters {'traffic.vehicle_count': 3}: reopening the arenas" in log
    wait_arenas_freed(server, timeout_s=20)


@needs_ml_side
def test_ml_agents_gym_wrapper_drives_overtake_through_the_bridge(pair, shared_server):
    server = shared_server
    pair.start_ml("gym", 30)
    pair.start_bridge(server.endpoint, "--set", *SHORT, "--behavior-name", "Highway")
    result = pair.ml_result()
    assert "error" not in result, result
    assert result["action_space"] == "Discrete(5)"
    # The wrapper's own arrangement: visual observations first, the vectors joined (360 + 6).
    assert result["obs_shapes"] == [[1, 80, 80], [366]] == result["space_shapes"]
    assert result["dones"] >= 2 and result["rewards"] == 30 and result["finite"]
    code, log = pair.bridge_exit()
    assert code == 0, log


# Slow (8 s: it waits out ML-Agents' own timeout); a terminated bridge telling ML-Agents at once
# and a dead trainer ending the bridge stay in the default run.
@pytest.mark.slow
@needs_ml_side
def test_a_bridge_that_dies_is_a_timeout_on_ml_agents_side(pair, shared_server):
    server = shared_server
    ml = pair.start_ml("hang")
    bridge = pair.start_bridge(server.endpoint)
    assert ml.stdout is not None
    assert json.loads(ml.stdout.readline()) == {"ready": True}
    stop_process(bridge, sig=9)
    assert ml.stdin is not None
    ml.stdin.write("go\n")
    ml.stdin.flush()
    result = pair.ml_result()
    assert result["error"] == "UnityTimeOutException", result
    assert result["after_s"] < 6 + 10  # timeout_wait 6 s, with slack for a loaded machine
    # The arenas of the killed bridge are freed when its Zenoh session's lease runs out.
    wait_arenas_freed(server, timeout_s=30)


@needs_ml_side
def test_a_trainer_that_dies_ends_the_bridge_with_a_clear_error(pair, shared_server):
    server = shared_server
    ml = pair.start_ml("hang")
    pair.start_bridge(server.endpoint)
    assert ml.stdout is not None
    assert json.loads(ml.stdout.readline()) == {"ready": True}
    stop_process(ml, sig=9)
    code, log = pair.bridge_exit()
    assert code == 1, log
    assert f"the ML-Agents process at 127.0.0.1:{pair.port} went away" in log
    assert server.probe().discover()[0].arenas_used == 0  # closed by the bridge on its way out


@needs_ml_side
def test_a_terminated_bridge_tells_ml_agents_at_once(pair, shared_server):
    server = shared_server
    ml = pair.start_ml("hang")
    bridge = pair.start_bridge(server.endpoint)
    assert ml.stdout is not None and ml.stdin is not None
    assert json.loads(ml.stdout.readline()) == {"ready": True}
    bridge.send_signal(signal.SIGTERM)
    code, log = pair.bridge_exit()
    assert code == 1 and "terminated (SIGTERM)" in log, log
    ml.stdin.write("go\n")
    ml.stdin.flush()
    result = pair.ml_result()
    assert result["error"] == "UnityCommunicatorStoppedException", result
    assert result["after_s"] < 5, result  # told, not its 6 s timeout
    wait_arenas_freed(server, timeout_s=20)


@needs_ml_side
def test_another_communication_version_is_refused_on_both_sides(pair, shared_server):
    server = shared_server
    pair.start_ml("version")
    pair.start_bridge(server.endpoint)
    result = pair.ml_result()
    assert result["error"] == "UnityEnvironmentException", result
    assert "1.5.0" in result["message"] and "2.0.0" in result["message"]
    code, log = pair.bridge_exit()
    assert code == 1
    assert "speaks communication version '2.0.0'" in log and "this bridge speaks 1.5.0" in log


@needs_ml_side
def test_an_override_the_server_refuses_stops_both_sides_saying_which(pair, shared_server):
    server = shared_server
    pair.start_ml("steps", 2)
    pair.start_bridge(server.endpoint, "--set", "traffic.no_such_setting=1")
    result = pair.ml_result()
    # Told at its first command (its reset), not left to time out.
    assert result["error"] == "UnityCommunicatorStoppedException", result
    assert result["after_s"] < 25, result
    code, log = pair.bridge_exit()
    assert code == 1 and "traffic.no_such_setting" in log, log


def test_no_ml_agents_process_listening_is_a_clear_error(tmp_path, shared_server):
    server = shared_server
    port = free_port()
    started = time.monotonic()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "overtake.client.mlagents.unity_bridge",
            "--connect",
            server.endpoint,
            "--port",
            str(port),
            "--host",
            "127.0.0.1",
            "--dial-timeout-s",
            "1",
        ],
        capture_output=True,
        text=True,
        env=child_env(),
        cwd=ROOT,
        timeout=60,
    )
    assert proc.returncode == 1
    assert f"no ML-Agents process listened on 127.0.0.1:{port} within 1 s" in proc.stderr
    assert time.monotonic() - started < 30
    assert server.probe().discover()[0].arenas_used == 0


@pytest.mark.slow
def test_mlagents_learn_trains_ppo_through_the_bridge():
    """scripts/try-mlagents-learn.sh from scratch: mlagents 1.1.0 in .venv-mlagents-learn, its
    PPO for 3,000 steps on min2018 through the bridge (about a minute with the install).
    mlagents-learn without --env listens on port 5004 of every interface, whatever it is told,
    and writes under runs/: the one test off a free loopback port, skipped where 5004 is taken."""
    if socket_taken(5004):
        pytest.skip("port 5004 is taken (mlagents-learn without --env listens there)")
    proc = subprocess.run(
        ["scripts/try-mlagents-learn.sh"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=child_env(),
        timeout=1800,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "min2018. Step: 3000." in proc.stdout
    assert "done after" in proc.stdout  # the bridge ended when mlagents-learn closed
    checkpoints = list((ROOT / "runs" / "mlagents-learn" / "ppo-min2018" / "min2018").glob("*.pt"))
    assert checkpoints, "no PyTorch checkpoint from mlagents-learn"
    # mlagents-learn finished with its own ONNX export, which ONNX Runtime loads and runs.
    assert "runs in ONNX Runtime" in proc.stdout


def socket_taken(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0

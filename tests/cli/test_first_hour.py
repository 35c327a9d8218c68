"""A new user's first hour (issue 59): each mistake at a command's edge gets one line that says
what was expected and what came, before any work starts."""

from __future__ import annotations

import importlib
import os
import shutil
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import torch

from overtake.cli import Output, UsageError, check_outputs
from overtake.client.wire.spectate import SpectateConfig
from overtake.client.wire.spectate import main as spectate_main
from overtake.ipc.endpoints import check_endpoints
from overtake.protocol.errors import ConnectError
from overtake.trainers.evaluate import COMMAND as evaluate_command
from overtake.viz.recording import RecordingConfig


def _exit_line(argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exited:
        evaluate_command.run(argv)
    message = str(exited.value.code)
    assert "\n" not in message and "Traceback" not in message, message
    return message


@pytest.mark.parametrize(
    ("written", "meant"),
    [
        ("127.0.0.1:7447", "tcp/127.0.0.1:7447"),
        ("tcp://127.0.0.1:7447", "tcp/127.0.0.1:7447"),
        ("tls://server.example:7447", "tls/server.example:7447"),
        ("localhost:7447", "tcp/localhost:7447"),
    ],
)
def test_an_endpoint_without_its_protocol_is_refused_with_the_corrected_form(written, meant):
    with pytest.raises(ConnectError, match=f"did you mean --connect {meant}\\?"):
        check_endpoints("--connect", (written,))
    check_endpoints("--connect", (meant,))  # the corrected form passes


def test_a_command_given_such_an_endpoint_says_so_before_connecting():
    message = _exit_line(["--policy", "rule", "--episodes", "1", "--connect", "127.0.0.1:7447"])
    assert message.startswith("overtake-eval: --connect 127.0.0.1:7447: an endpoint is")
    assert "tcp/127.0.0.1:7447" in message and "could not connect" not in message


def test_a_typo_in_a_setting_names_the_setting_meant_in_a_short_line():
    message = _exit_line(["--policy", "rule", "--episodes", "1", "--set", "traffic.densty=heavy"])
    assert "did you mean traffic.density?" in message
    assert len(message) < 600, len(message)
    # A name nothing resembles gets no guess, only some of the names there are.
    message = _exit_line(["--policy", "rule", "--episodes", "1", "--set", "zzz.qqq=1"])
    assert "did you mean" not in message and "more)" in message and len(message) < 600


@pytest.mark.parametrize("kind", ["text", "pickle"])
def test_a_file_that_is_not_a_checkpoint_gets_one_line_and_no_unsafe_advice(tmp_path, kind):
    path = tmp_path / "model.pt"
    if kind == "text":
        path.write_text("these are my notes, not a model\n")
    else:  # a pickle of objects PyTorch's safe loader refuses (it advises weights_only=False)
        torch.save({"optimiser": torch.optim.SGD([torch.zeros(1)], lr=0.1)}, path)
    message = _exit_line(["--checkpoint", str(path), "--episodes", "1"])
    assert message.startswith(f"overtake-eval: {path} is not a checkpoint overtake-train wrote")
    assert "weights_only" not in message


def test_the_pettingzoo_faces_without_pettingzoo_name_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pettingzoo", None)  # as if not installed
    for name in ("overtake.envs.parallel_face", "overtake.server.engine.parallel_env"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    with pytest.raises(ModuleNotFoundError, match=r'pip install -e "\.\[pettingzoo\]"') as error:
        importlib.import_module("overtake.server.engine.parallel_env")
    assert error.value.name == "pettingzoo"


def test_spectate_refuses_to_overwrite_the_last_recording(tmp_path: Path):
    """The earlier recording is left as it was, and nothing is connected to first."""
    earlier = tmp_path / "world.rrd"
    earlier.write_bytes(b"an earlier recording")
    config = SpectateConfig(
        connect=("tcp/127.0.0.1:9",), recording=RecordingConfig(rrd=earlier), seconds=0.1
    )
    with pytest.raises(UsageError, match=r"world\.rrd exists .*--overwrite to replace it"):
        spectate_main(config)
    assert earlier.read_bytes() == b"an earlier recording"


ROOT = Path(__file__).resolve().parents[2]


def _fake_python(path: Path, version: str) -> Path:
    """A stand-in for a Python of ``version``: answers the version query, makes a venv of
    itself, and notes each pip install instead of installing."""
    path.write_text(
        "#!/usr/bin/env bash\n"
        f'if [[ "$1" == "-c" ]]; then echo "{version}"; exit 0; fi\n'
        'if [[ "$1 $2" == "-m venv" ]]; then mkdir -p "$3/bin"; cp "$0" "$3/bin/python";'
        " exit 0; fi\n"
        'if [[ "$1 $2" == "-m pip" ]]; then echo "$0 $*" >> pip.log; exit 0; fi\n'
        "exit 3\n"
    )
    path.chmod(0o755)
    return path


def _setup(root: Path, python: Path | None) -> subprocess.CompletedProcess[str]:
    (root / "scripts").mkdir(exist_ok=True)
    shutil.copy(ROOT / "scripts" / "setup.sh", root / "scripts" / "setup.sh")
    env = {k: v for k, v in os.environ.items() if k != "PYTHON"}
    if python is not None:
        env["PYTHON"] = str(python)
    return subprocess.run(
        ["bash", "scripts/setup.sh", "dev"],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_set_up_refuses_an_old_python_before_installing_anything(tmp_path):
    old = _fake_python(tmp_path / "python3.10", "3.10")
    done = _setup(tmp_path, old)
    assert done.returncode == 1
    assert f"overtake needs Python 3.11 or newer; {old} is 3.10" in done.stderr
    assert "PYTHON=python3.11" in done.stderr
    assert not (tmp_path / ".venv").exists() and not (tmp_path / "pip.log").exists()


def test_set_up_replaces_a_venv_another_python_made_and_says_so(tmp_path):
    _fake_python(tmp_path / "python3.10", "3.10")
    (tmp_path / ".venv" / "bin").mkdir(parents=True)
    shutil.copy(tmp_path / "python3.10", tmp_path / ".venv" / "bin" / "python")
    new = _fake_python(tmp_path / "python3.11", "3.11")
    done = _setup(tmp_path, new)
    assert done.returncode == 0, done.stderr
    assert "made by Python 3.10" in done.stderr and "replacing it" in done.stderr
    assert "3.11" in (tmp_path / ".venv" / "bin" / "python").read_text()
    assert "torch==2.13.0" in (tmp_path / "pip.log").read_text()
    # Run again: the venv is the wanted one, kept without a word.
    done = _setup(tmp_path, new)
    assert done.returncode == 0 and "replacing" not in done.stderr
    # Without PYTHON, a recent enough venv is kept even where python3 is old.
    done = _setup(tmp_path, None)
    assert done.returncode == 0 and "replacing" not in done.stderr


COMMANDS = tuple(
    name
    for name in tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
        "scripts"
    ]
)


def _help_into_a_closed_pipe(commands: tuple[str, ...]) -> None:
    """``--help | head -1`` for each of ``commands``: the first line, and nothing on stderr (no
    BrokenPipeError). The pipelines, one a command, run at once (each starts an interpreter)."""
    running = {
        command: subprocess.Popen(
            ["bash", "-c", f'"{Path(sys.executable).parent / command}" --help | head -1'],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for command in commands
    }
    for command, process in running.items():
        out, err = process.communicate(timeout=120)
        assert out.startswith("usage:"), (command, out, err)
        assert err == "", (command, err)


def test_help_into_a_closed_pipe_ends_quietly():
    """Two commands through the one door: one that loads PyTorch, one that does not (every
    command: the slow test below)."""
    assert {"overtake-server", "overtake-eval"} <= set(COMMANDS)
    _help_into_a_closed_pipe(("overtake-server", "overtake-eval"))


@pytest.mark.slow  # an interpreter a command, half of them loading PyTorch: 10 s of both cores
def test_every_commands_help_into_a_closed_pipe_ends_quietly():
    _help_into_a_closed_pipe(COMMANDS)


def test_an_output_that_cannot_be_written_is_refused_before_any_episode(tmp_path, monkeypatch):
    import overtake.trainers.evaluate as evaluate

    def never(config):
        raise AssertionError("main ran: the output was not checked first")

    monkeypatch.setattr(evaluate, "main", never)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a folder")
    message = _exit_line(
        ["--policy", "rule", "--episodes", "1", "--json-out", str(a_file / "x.json")]
    )
    assert (
        message
        == f"overtake-eval: --json-out {a_file / 'x.json'}: {a_file} is a file, not a folder"
    )
    message = _exit_line(["--policy", "rule", "--episodes", "1", "--episodes-out", str(a_file)])
    assert message.endswith("a file is there, expected a folder")
    message = _exit_line(["--policy", "rule", "--episodes", "1", "--record", str(tmp_path)])
    assert message.endswith("a folder is there, expected a file")


def test_a_grpc_sink_with_no_viewer_is_refused_at_once_naming_what_to_start():
    """Before connecting to anything: nothing would be recorded, and the exit would stall."""
    from tests.support.remote import free_port

    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    done = subprocess.run(
        [
            str(Path(sys.executable).parent / "overtake-spectate"),
            "--connect",
            f"tcp/127.0.0.1:{free_port()}",
            "--sink",
            "grpc",
            "--viewer-url",
            url,
            "--seconds",
            "30",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert done.stderr.startswith(f"overtake-spectate: no Rerun viewer listens at {url}")
    assert "rerun" in done.stderr and done.stderr.count("\n") == 1, done.stderr
    # Where one listens, the same check passes.
    with socket.create_server(("127.0.0.1", 0)) as viewer:
        port = viewer.getsockname()[1]
        check_outputs(
            [Output("--viewer-url", None, viewer_url=f"rerun+http://127.0.0.1:{port}/proxy")]
        )


def test_a_recording_without_a_footer_opens_without_rerun_s_warning(tmp_path, capfd):
    """Long-running processes write .rrd files without a footer, a choice explained in
    docs/rerun.md: Rerun's warning about it, at every such file, is not shown."""
    from overtake.viz.recording import APPLICATION_ID, close_recording, open_recording

    rrd = tmp_path / "long.rrd"
    recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=rrd), rrd, footer=False)
    close_recording(recording)
    assert rrd.stat().st_size > 0
    assert "write_footer" not in capfd.readouterr().err


def test_every_option_of_every_command_says_what_it_is():
    """Each field of each command's configuration (nested ones too) has the docstring its
    --help line shows (22 had none)."""
    import dataclasses
    import typing

    from tyro._docstrings import get_field_docstring

    from overtake.client.episodes.drive import DriveConfig
    from overtake.client.mlagents.unity_bridge import BridgeConfig
    from overtake.client.wire.status import StatusConfig
    from overtake.server.router import RouterConfig
    from overtake.server.service.server_config import ServerConfig
    from overtake.trainers.collision_causes import CausesConfig
    from overtake.trainers.config.train_config import TrainConfig
    from overtake.trainers.episode_replay import ReplayConfig
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.experiment.plan import ExperimentConfig
    from overtake.trainers.export import ExportConfig
    from overtake.viz.layout import LayoutConfig
    from overtake.viz.render import RenderConfig

    def undocumented(cls: type, prefix: str = "") -> list[str]:
        hints = typing.get_type_hints(cls, include_extras=True)
        found = []
        for field in dataclasses.fields(cls):
            hint = hints[field.name]
            if typing.get_origin(hint) is typing.Annotated:
                hint = typing.get_args(hint)[0]
            if dataclasses.is_dataclass(hint):
                found += undocumented(hint, f"{prefix}{field.name}.")
            elif not get_field_docstring(cls, field.name, ()):
                found.append(f"{cls.__name__}.{prefix}{field.name}")
        return found

    configs = (
        DriveConfig, BridgeConfig, StatusConfig, RouterConfig, ServerConfig, ReplayConfig,
        EvalConfig, ExperimentConfig, ExportConfig, TrainConfig, LayoutConfig, RenderConfig,
        SpectateConfig, CausesConfig,
    )  # fmt: skip
    assert [name for config in configs for name in undocumented(config)] == []


def test_a_run_that_cannot_start_leaves_no_empty_run_directory(tmp_path):
    from overtake.trainers.train import COMMAND as train_command

    run_dir = tmp_path / "runs" / "first"
    with pytest.raises(SystemExit) as exited:
        train_command.run(
            ["--run-dir", str(run_dir), "--set", "traffic.densty=heavy", "--no-progress"]
        )
    assert "did you mean traffic.density?" in str(exited.value.code)
    assert not run_dir.exists()


def test_the_router_refuses_such_an_endpoint_too():
    """overtake-router builds its Zenoh configuration itself: the same check, not Zenoh's
    Json5Err traceback."""
    from overtake.server.router import RouterConfig, zenoh_config

    with pytest.raises(ConnectError, match=r"did you mean --connect tcp/127\.0\.0\.1:7447\?"):
        zenoh_config(RouterConfig(connect=("127.0.0.1:7447",)))

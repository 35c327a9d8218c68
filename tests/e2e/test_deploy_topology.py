"""Deployment topologies without Docker: the compose file's router, server and three trainers
as processes, then an evaluation; and a trainer on another network host (a network
namespace the test creates) reaching the router.

Every process is real (``python -m ...`` of the installed commands) on 127.0.0.1 with free
ports; each is ended by its PID, and every wait is on a condition with a deadline
(``tests.support.remote.wait_until``), never a fixed sleep.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from overtake.client.wire.remote import RemoteConfig

from tests.support import deploy
from tests.support.remote import free_port, stop_process, wait_until

# Credentials in the developer's environment must not leak into these tests.
pytestmark = pytest.mark.usefixtures("no_inherited_credentials")


# --- the compose topology, without Docker ------------------------------------------------------


# About 12 s on an idle 2-core machine (four PyTorch processes): the compose file's topology, as
# processes. Slow: the usrpwd and TLS tests (test_deploy_users.py, test_deploy_tls.py) run a
# router, a server and a trainer by default; this adds the three trainers and the evaluation.
@pytest.mark.slow
@pytest.mark.timeout(400)
def test_router_server_and_three_trainers_then_eval(tmp_path: Path, background):
    router_ep = f"tcp/{deploy.LOOPBACK}:{free_port()}"
    deploy.start_router(background, "router", [router_ep])
    server = deploy.start_server(background, "sim-topology", router_ep)
    deploy.wait_for_server(
        "sim-topology", RemoteConfig(connect=(router_ep,), connect_timeout_s=10.0), server
    )

    trainers = {}
    for algo in ("dqn", "ddqn", "dueling"):
        run_dir = tmp_path / "runs" / algo
        # Closed below, once the trainers have exited.
        out = open(tmp_path / f"{algo}.out", "w+")  # noqa: SIM115
        err = open(tmp_path / f"{algo}.err", "w+")  # noqa: SIM115
        proc = subprocess.Popen(
            deploy.train_argv(algo, router_ep, run_dir),
            cwd=deploy.ROOT,
            env=deploy.env_with(),
            stdout=out,
            stderr=err,
            text=True,
        )
        trainers[algo] = (proc, run_dir, out, err)
    summaries = []
    try:
        for proc, run_dir, out, err in trainers.values():
            code = proc.wait(timeout=deploy.COMMAND_TIMEOUT_S)
            out.seek(0)
            err.seek(0)
            summaries.append(
                deploy.check_trained(
                    subprocess.CompletedProcess(proc.args, code, out.read(), err.read()), run_dir
                )
            )
    finally:
        for proc, _, out, err in trainers.values():
            stop_process(proc)
            out.close()
            err.close()

    # Every step a trainer took through the router is one round the server played for it,
    # no more, no less (the server says how many as each trainer leaves).
    for summary in summaries:
        assert summary["server_losses"] == 0
        # With overlap a trainer's arenas are two groups: its sends are their rounds together.
        pattern = (
            rf"trainer {re.escape(summary['trainer'])} left group \d+ \(closed\); arenas \S+ "
            r"freed after (\d+) rounds"
        )
        wait_until(
            lambda p=pattern, n=summary["parts"]: len(re.findall(p, server.log_text())) == n,
            timeout_s=30,
            what=f"the server freeing trainer {summary['trainer']}'s groups",
        )
        rounds = re.findall(pattern, server.log_text())
        assert sum(int(r) for r in rounds) == summary["env_steps_called"] > 0

    report = tmp_path / "eval.json"
    done = deploy.run(
        [
            deploy.PY,
            "-m",
            "overtake.trainers.evaluate",
            "--checkpoint",
            str(tmp_path / "runs" / "dueling" / "checkpoint.pt"),
            "--episodes",
            "2",
            "--max-decisions",
            "30",
            "--connect",
            router_ep,
            "--json-out",
            str(report),
        ]
    )
    assert done.returncode == 0, done.stderr[-4000:]
    result = json.loads(report.read_text())
    assert result["name"].startswith("dueling/lidar@") and len(result["episodes"]) == 2


# --- a trainer on another host: a network namespace --------------------------------------------


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


@pytest.fixture
def remote_host() -> Iterator[tuple[str, str, str]]:
    """A network namespace joined to this one by a veth pair on a private /30: yields (namespace,
    this side's address, its address). Removed afterwards, whatever happened."""
    if shutil.which("ip") is None:
        pytest.skip("the ip command (iproute2) is not installed")
    if os.geteuid() != 0:
        pytest.skip("creating a network namespace needs root")
    tag = f"{os.getpid() % 100000}{secrets.token_hex(1)}"
    namespace, host_if, ns_if = f"overtake-{tag}", f"ovh{tag}", f"ovn{tag}"
    # 10.a.b.0/30, in a /24 no interface of this host uses yet.
    used = _ip("-4", "-o", "addr", check=False).stdout
    prefix = next(
        (f"10.{a}.{b}" for a in range(200, 250) for b in range(256) if f" 10.{a}.{b}." not in used),
        None,
    )
    assert prefix is not None, "no free 10.x.y.0/24 for the link"
    host_ip, ns_ip = f"{prefix}.1", f"{prefix}.2"
    added = _ip("netns", "add", namespace, check=False)
    if added.returncode != 0:
        pytest.skip(f"cannot create a network namespace here: {added.stderr.strip()}")
    try:
        _ip("link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        _ip("link", "set", ns_if, "netns", namespace)
        _ip("addr", "add", f"{host_ip}/30", "dev", host_if)
        _ip("link", "set", host_if, "up")
        _ip("netns", "exec", namespace, "ip", "addr", "add", f"{ns_ip}/30", "dev", ns_if)
        _ip("netns", "exec", namespace, "ip", "link", "set", ns_if, "up")
        _ip("netns", "exec", namespace, "ip", "link", "set", "lo", "up")
        yield namespace, host_ip, ns_ip
    finally:
        _ip("netns", "del", namespace, check=False)  # takes its end of the pair along
        _ip("link", "del", host_if, check=False)


@pytest.mark.timeout(240)
def test_trainer_in_another_network_namespace_reaches_the_router(
    tmp_path: Path, background, remote_host
):
    namespace, host_ip, _ns_ip = remote_host
    port = free_port()
    loopback_ep, veth_ep = f"tcp/{deploy.LOOPBACK}:{port}", f"tcp/{host_ip}:{port}"
    # The router listens on loopback (for the server) and on the link the other host sees.
    deploy.start_router(background, "router", [loopback_ep, veth_ep])
    server = deploy.start_server(background, "sim-netns", loopback_ep)
    deploy.wait_for_server(
        "sim-netns", RemoteConfig(connect=(loopback_ep,), connect_timeout_s=10.0), server
    )
    # Nothing on loopback inside the namespace: only the veth link leads to the router.
    blocked = deploy.run(
        [
            "ip",
            "netns",
            "exec",
            namespace,
            deploy.PY,
            "-m",
            "overtake.client.wire.status",
            "--connect",
            loopback_ep,
            "--timeout-s",
            "1",
        ],
        timeout_s=60,
    )
    assert blocked.returncode != 0 and "nothing accepts connections" in blocked.stderr.lower(), (
        blocked.stderr
    )

    run_dir = tmp_path / "runs" / "netns"
    done = deploy.run(
        ["ip", "netns", "exec", namespace, *deploy.train_argv("ddqn", veth_ep, run_dir)]
    )
    summary = deploy.check_trained(done, run_dir)
    assert summary["steps"] >= 200
    record = json.loads((run_dir / "run.json").read_text())
    assert record["config"]["where"]["connect"] == [veth_ep]

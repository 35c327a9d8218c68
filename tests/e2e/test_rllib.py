"""Scale-out on Ray: RLlib's DQN (examples/rllib_dqn.py) on a local Ray cluster, its env runners
opening arenas on two simulator servers on 127.0.0.1."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.remote import child_env, wait_until

pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (the rllib extra)")

ROOT = Path(__file__).resolve().parents[2]


# Slow (about 30 s, most of it Ray starting its cluster): the default suite stays under 7
# minutes on 2 cores; `pytest -m slow` runs it.
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_rllib_env_runners_share_two_servers_and_learn(start_server):
    servers = [start_server("rllib-a"), start_server("rllib-b")]
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "examples" / "rllib_dqn.py"),
            "--connect",
            *(s.endpoint for s in servers),
            "--env-runners",
            "2",
            "--iterations",
            "1",
            "--learning-starts",
            "100",
            "--num-cpus",
            "2",
            "--set",
            "episode.max_decisions=50",
        ],
        capture_output=True,
        text=True,
        timeout=500,
        env=child_env(),
        cwd=ROOT,
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    # One RLlib iteration: 1,000 environment steps sampled by the two runners together.
    sampled = re.search(r"'env_steps_sampled': ([\d.]+)", output)
    assert sampled and float(sampled.group(1)) >= 1000, output[-2000:]
    assert re.search(r"'episode_return_mean': np\.float64\(-?[\d.]+\)", output), output[-2000:]
    # Each runner opened its arena on its own server; both are freed once Ray has shut down.
    for runner, server in enumerate(servers, start=1):
        assert f"trainer rllib-runner-{runner}-" in server.log_text(), server.log_text()[-2000:]
        wait_until(lambda s=server: s.status().arenas_used == 0, 10.0, "arenas freed")

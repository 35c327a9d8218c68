"""Deployment with users: a usrpwd router admits only the users it lists, and with
--isolate-trainers each trainer reaches only its own arenas (Zenoh access control by user).

Every process is real (``python -m ...`` of the installed commands) on 127.0.0.1 with free
ports; each is ended by its PID, and every wait is on a condition with a deadline
(``tests.support.remote.wait_until``), never a fixed sleep.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from overtake.client.wire.remote import Connection, RemoteConfig
from overtake.ipc.transport import PASSWORD_ENV, USER_ENV, SecurityConfig, TransportConfig
from overtake.protocol import errors
from overtake.server.router import RouterConfig, zenoh_config

from tests.support import deploy
from tests.support.remote import free_port, wait_until

# Credentials in the developer's environment must not leak into these tests.
pytestmark = pytest.mark.usefixtures("no_inherited_credentials")


def test_usrpwd_router_admits_only_listed_users(tmp_path: Path, background):
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:server-secret\ntrainer:trainer-secret\n")
    server_password = tmp_path / "server.pw"
    server_password.write_text("server-secret\n")
    port = free_port()
    router_ep = f"tcp/{deploy.LOOPBACK}:{port}"
    deploy.start_router(background, "router", [router_ep], "--credentials-file", str(credentials))
    # The server's password from a file, the trainer's from the environment: neither appears on
    # a command line. The server listens nowhere (docs/remote-hosts.md's recipe): nobody gets to it
    # without passing the router's check.
    server = deploy.start_server(
        background,
        "sim-auth",
        router_ep,
        "--user",
        "simserver",
        "--password-file",
        str(server_password),
        listen=False,
    )
    deploy.wait_for_server(
        "sim-auth",
        RemoteConfig(
            connect=(router_ep,),
            connect_timeout_s=10.0,
            security=SecurityConfig(user="simserver", password_file=server_password),
        ),
        server,
    )
    assert f"(peer connecting to {router_ep})" in server.log_text()

    run_dir = tmp_path / "runs" / "ddqn"
    done = deploy.run(
        deploy.train_argv("ddqn", router_ep, run_dir, "--user", "trainer"),
        deploy.env_with(**{PASSWORD_ENV: "trainer-secret"}),
    )
    deploy.check_trained(done, run_dir)
    record = (run_dir / "run.json").read_text()
    assert '"user": "trainer"' in record and "trainer-secret" not in record

    # A wrong password: refused, and the message names it as the likely cause.
    refused = deploy.run(
        [
            deploy.PY,
            "-m",
            "overtake.client.wire.status",
            "--connect",
            router_ep,
            "--timeout-s",
            "1",
        ],
        deploy.env_with(**{USER_ENV: "trainer", PASSWORD_ENV: "not-the-password"}),
        timeout_s=60,
    )
    assert refused.returncode != 0
    assert "wrong password for user 'trainer'" in refused.stderr, refused.stderr
    # No credentials at all.
    with pytest.raises(errors.ConnectError, match="requires usrpwd credentials"):
        Connection(RemoteConfig(connect=(router_ep,), connect_timeout_s=1.0))


@pytest.mark.slow  # the server says so only after its 10 s of trying (ipc.transport)
@pytest.mark.timeout(120)
def test_a_server_with_the_wrong_password_keeps_trying_and_says_why(tmp_path: Path, background):
    """A server with the wrong password keeps trying in the background (it may have started
    before its router), and says why it is still alone after 10 s."""
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:server-secret\n")
    router_ep = f"tcp/{deploy.LOOPBACK}:{free_port()}"
    deploy.start_router(background, "router", [router_ep], "--credentials-file", str(credentials))
    wrong_password = tmp_path / "wrong.pw"
    wrong_password.write_text("not-the-password\n")
    lonely = deploy.start_server(
        background,
        "sim-lonely",
        router_ep,
        "--user",
        "simserver",
        "--password-file",
        str(wrong_password),
    )
    lonely.wait_log("not connected to", timeout_s=30)
    assert "wrong password for user 'simserver'" in lonely.log_text()


@pytest.mark.timeout(180)
def test_isolated_trainers_reach_only_their_own_arenas(tmp_path: Path, background):
    # overtake-router --isolate-trainers: Zenoh access control by usrpwd user. Bob's session
    # asks for everything (every trainer's steps, every action, the world frames) and gets
    # only his own trainer's steps; the spectator user watches the world; the same
    # subscriptions on a router without isolation see Alice's steps (the test can fail).
    import gymnasium as gym

    import overtake.client  # noqa: F401  (registers the environments)
    from overtake.client.wire.world_feed import Spectator
    from overtake.envs import REMOTE_HIGHWAY_ENV_ID as REMOTE_ENV
    from overtake.ipc.transport import open_session
    from overtake.protocol import keys

    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:s3rver\nwatcher:w4tch\nalice:al1ce\nbob:b0b\n")
    passwords = {}
    for user, password in (line.split(":") for line in credentials.read_text().split()):
        passwords[user] = tmp_path / f"{user}.pw"
        passwords[user].write_text(password + "\n")

    def security(user: str) -> SecurityConfig:
        return SecurityConfig(user=user, password_file=passwords[user])

    def remote(user: str) -> RemoteConfig:
        # Over Zenoh: what is tested is what the router lets cross it. On the server's host
        # the trainers would otherwise step through shared memory, and no round would cross.
        return RemoteConfig(
            connect=(endpoint,),
            connect_timeout_s=10.0,
            request_timeout_s=5.0,
            step_timeout_s=20.0,
            security=security(user),
            transport="zenoh",
        )

    def seen_by_bob() -> tuple[set[str], int]:
        """The keys of every sample Bob's spying session received while Alice and Bob each
        stepped a remote arena, and the world frames the spectator user received."""
        spy = open_session(
            TransportConfig(mode="client", connect=(endpoint,), security=security("bob"))
        )
        received: list[str] = []
        try:
            # Everything, every trainer's steps, the world, and (allowed) bob's own steps.
            wanted_keys = ("overtake/**", "overtake/trainer/*/steps/*", keys.world_all())
            for wanted in (*wanted_keys, "overtake/trainer/bob-$*/steps/*"):
                spy.declare_subscriber(wanted, lambda sample: received.append(str(sample.key_expr)))
            bob_env = gym.make_vec(REMOTE_ENV, num_envs=1, preset="ho2018", remote=remote("bob"))
            alice_env = gym.make_vec(
                REMOTE_ENV, num_envs=1, preset="ho2018", remote=remote("alice")
            )
            with Spectator(remote("watcher")) as spectator:
                bob_env.reset(seed=1)
                alice_env.reset(seed=2)
                mine = f"overtake/trainer/{bob_env.unwrapped.trainer}/steps/sim-iso"

                def bob_steps_seen() -> int:
                    bob_env.step([0])
                    return received.count(mine)

                # Bob's own steps reach his spy: its subscriptions are in place.
                wait_until(bob_steps_seen, 30, "bob's spy receiving bob's own steps")
                for _ in range(30):
                    alice_env.step([0])
                # The router sends the spy what it is allowed in order on one link: once a
                # step of bob's after alice's has arrived, so has anything of alice's.
                before = received.count(mine)
                wait_until(lambda: bob_steps_seen() > before, 30, "bob's step after alice's")
                assert spectator.next_frame(30.0) is not None
                world_frames = spectator.frames_received
            assert alice_env.unwrapped.trainer.startswith(
                "alice-"
            ) and bob_env.unwrapped.trainer.startswith("bob-")
            alice_env.close()
            bob_env.close()
        finally:
            spy.close()
        return set(received), world_frames

    credentials_args = ("--credentials-file", str(credentials))
    roles = ("--isolate-trainers", "--server-users", "simserver", "--spectator-users", "watcher")
    for isolate in (True, False):
        endpoint = f"tcp/{deploy.LOOPBACK}:{free_port()}"
        router = deploy.start_router(
            background,
            f"router-isolate-{isolate}",
            [endpoint],
            *credentials_args,
            *(roles if isolate else ()),
        )
        server = deploy.start_server(
            background,
            f"server-{isolate}",
            endpoint,
            *("--name", "sim-iso", "--user", "simserver", "--password-file"),
            str(passwords["simserver"]),
            listen=False,
        )
        deploy.wait_for_server("sim-iso", remote("simserver"), server)
        seen, world_frames = seen_by_bob()
        assert world_frames > 0  # the spectator user watches the world either way
        if isolate:
            assert "trainers isolated: servers ['simserver'], spectators ['watcher'], " in (
                router.log_text()
            )
            assert seen and all(key.startswith("overtake/trainer/bob-") for key in seen), seen
        else:
            assert any(key.startswith("overtake/trainer/alice-") for key in seen), seen
            assert any("/world/" in key for key in seen), seen
        router.stop()
        server.stop()


def test_isolation_settings_are_checked_with_the_user_named(tmp_path: Path):
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:a\nalice:b\nbob-the-builder:c\n")

    def router(**changes) -> RouterConfig:
        return RouterConfig(
            security=SecurityConfig(credentials_file=credentials),
            isolate_trainers=True,
            server_users=("simserver",),
            **changes,
        )

    with pytest.raises(errors.ConnectError, match="'bob-the-builder' cannot be isolated"):
        zenoh_config(router())
    credentials.write_text("simserver:a\nalice:b\n")
    conf, _ = zenoh_config(router())
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert [s["usernames"] for s in acl["subjects"]] == [["simserver"], ["alice"]]
    with pytest.raises(errors.ConnectError, match=r"\['nobody'\] are not in"):
        zenoh_config(router(spectator_users=("nobody",)))
    with pytest.raises(errors.ConnectError, match="give --credentials-file"):
        zenoh_config(RouterConfig(isolate_trainers=True, server_users=("simserver",)))
    with pytest.raises(errors.ConnectError, match="need --isolate-trainers"):
        zenoh_config(RouterConfig(server_users=("simserver",)))
    # The example for zenohd in docker/ is what the router makes for its users.
    example = (deploy.ROOT / "docker" / "zenoh-router-isolated.json5").read_text()
    from overtake.server.service.access import isolation_rules

    body = json.loads(re.sub(r"^\s*//.*$", "", example, flags=re.M))
    assert body["access_control"] == isolation_rules(["simserver"], ["watcher"], ["alice", "bob"])

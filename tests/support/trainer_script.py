"""A small trainer for the end-to-end tests, run as a subprocess.

It opens arenas (or joins one) through :class:`overtake.client.RemoteEnvironment`, prints
``READY {json}`` and then obeys commands read from stdin, one per line:

``step N``  step N decisions, then print ``STEPPED {json}``
``run``     step until ``stop`` (or ``exit``) arrives, then print ``STOPPED {json}``
``close``   close the environment (``CLOSED``)
``exit``    close and exit 0

Every event is one line ``EVENT {json}`` on stdout, flushed, so a test can wait on lines with a
deadline. ``STEP`` lines (every ``--print-every`` steps) describe one step; an exception is
reported as ``ERROR {"type", "message"}`` and the script keeps obeying commands.
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from typing import Any

import numpy as np

from overtake.client import ActionTuple, RemoteConfig, RemoteEnvironment


def emit(event: str, **fields: Any) -> None:
    sys.stdout.write(f"{event} {json.dumps(fields, default=_plain)}\n")
    sys.stdout.flush()


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot print {type(value).__name__}")


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--connect", required=True)
    p.add_argument("--server", default=None)
    p.add_argument("--preset", default="min2018")
    p.add_argument("--overrides", default="{}", help="JSON object of overrides")
    p.add_argument("--arenas", type=int, default=1)
    p.add_argument("--agents-per-arena", type=int, default=1)
    p.add_argument("--claim", type=int, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--join", type=int, default=None, help="join this arena id instead")
    p.add_argument("--policy", choices=("keep", "random"), default="keep")
    p.add_argument("--print-every", type=int, default=1)
    p.add_argument("--print-lidar", action="store_true", help="full LIDAR rows in STEP lines")
    p.add_argument("--connect-timeout-s", type=float, default=10.0)
    p.add_argument("--step-timeout-s", type=float, default=20.0)
    p.add_argument("--reconnect-timeout-s", type=float, default=0.0)
    p.add_argument("--trainer-name", default="e2e")
    p.add_argument("--lease-s", type=float, default=3.0)
    return p.parse_args(argv)


class Trainer:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        config = RemoteConfig(
            connect=(args.connect,),
            server=args.server,
            connect_timeout_s=args.connect_timeout_s,
            request_timeout_s=5.0,
            step_timeout_s=args.step_timeout_s,
            reconnect_timeout_s=args.reconnect_timeout_s,
            trainer_name=args.trainer_name,
            lease_s=args.lease_s,
        )
        self.env = RemoteEnvironment(
            preset=args.preset,
            overrides=json.loads(args.overrides),
            arenas=args.arenas,
            agents_per_arena=args.agents_per_arena,
            claim=args.claim,
            seed=args.seed,
            join=args.join,
            config=config,
        )
        self.name = next(iter(self.env.behavior_specs))
        self.rng = np.random.default_rng(args.seed)
        self.steps_done = 0
        self.late_seen = 0
        self.closed = False

    def ready(self) -> None:
        group = self.env.group
        steps = self.env.steps
        emit(
            "READY",
            trainer=group.connection.trainer,
            server=group.server,
            group=group.group_id,
            arena_ids=list(group.arena_ids),
            agents=steps.agents,
            round=group.round,
            observations=[s.name for s in self.env.behavior_specs[self.name].observation_specs],
        )

    def one_step(self) -> dict[str, Any]:
        decision, _ = self.env.get_steps(self.name)
        n = len(decision)
        if self.args.policy == "random":
            values = self.rng.integers(0, 5, size=(n, 1))
        else:
            values = np.zeros((n, 1), dtype=np.int32)
        self.env.set_actions(self.name, ActionTuple(discrete=values))
        restarts = self.env.group.restarts
        self.env.step()
        self.steps_done += 1
        s = self.env.steps
        self.late_seen += int(s.late.sum())
        info: dict[str, Any] = dict(
            i=self.steps_done,
            round=self.env.group.round,
            t=time.monotonic(),
            agents=s.agents,
            reward=s.reward,
            terminated=s.terminated,
            truncated=s.truncated,
            late=s.late,
            applied=s.action_applied,
            restarted=self.env.group.restarts != restarts,
            restarts=self.env.group.restarts,
        )
        if "lidar" in s.observations:
            lidar = s.observations["lidar"]
            info["min_lidar"] = lidar.min(axis=1)
            if self.args.print_lidar:
                info["lidar"] = lidar
        return info

    def run(self, count: int | None, commands: queue.Queue[str]) -> tuple[dict[str, Any], str]:
        """Step ``count`` times (None: until a command arrives); the summary and the command
        that stopped it (``""`` when the count was reached)."""
        start = time.monotonic()
        last_t = start
        max_gap = 0.0
        done = 0
        info: dict[str, Any] = {}
        stopped_by = ""
        while count is None or done < count:
            if count is None:
                try:
                    stopped_by = commands.get_nowait()
                    break
                except queue.Empty:
                    pass
            info = self.one_step()
            done += 1
            now = info["t"]
            max_gap = max(max_gap, now - last_t)
            last_t = now
            if done % self.args.print_every == 0 or info["restarted"]:
                emit("STEP", **info)
        summary = dict(
            steps=done,
            total_steps=self.steps_done,
            round=self.env.group.round,
            t0=start,
            t1=time.monotonic(),
            max_gap_s=max_gap,
            late_seen=self.late_seen,
            restarts=self.env.group.restarts,
            last=info,
        )
        return summary, stopped_by

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.env.close()


def read_commands(commands: queue.Queue[str]) -> None:
    for line in sys.stdin:
        line = line.strip()
        if line:
            commands.put(line)
    commands.put("exit")  # stdin closed: the test is gone


def main() -> int:
    args = parse()
    try:
        trainer = Trainer(args)
    except Exception as error:
        emit("ERROR", type=type(error).__name__, message=str(error), phase="open")
        return 2
    commands: queue.Queue[str] = queue.Queue()
    threading.Thread(target=read_commands, args=(commands,), daemon=True).start()
    trainer.ready()
    try:
        while True:
            command = commands.get()
            word, _, rest = command.partition(" ")
            try:
                if word == "step":
                    summary, _ = trainer.run(int(rest or 1), commands)
                    emit("STEPPED", **summary)
                elif word == "run":
                    summary, stopped_by = trainer.run(None, commands)
                    emit("STOPPED", **summary)
                    if stopped_by == "exit":
                        break
                elif word == "close":
                    trainer.close()
                    emit("CLOSED")
                elif word == "exit":
                    break
                elif word == "stop":
                    emit("STOPPED", steps=0)
                else:
                    emit("ERROR", type="UnknownCommand", message=command)
            except Exception as error:
                emit(
                    "ERROR",
                    type=type(error).__name__,
                    message=str(error),
                    t=time.monotonic(),
                    steps=trainer.steps_done,
                )
    finally:
        try:
            trainer.close()
        except Exception as error:  # the server may be gone
            emit("CLOSE_ERROR", type=type(error).__name__, message=str(error))
    emit("EXIT")
    return 0


if __name__ == "__main__":
    sys.exit(main())

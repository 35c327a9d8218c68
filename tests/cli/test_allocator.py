"""Every command's allocator settings (cli/allocator.py, applied at the door): a block of a few
MiB freed and allocated again reuses its pages instead of faulting in fresh ones."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from overtake.cli import allocator

# Allocates six arrays of 4 MiB (written through, as an update's tensors are, all live at once
# as in a backward pass), frees them, 50 times over, and prints the minor page faults that
# cost, after applying the settings or not.
_FAULTS = """
import importlib.util, json, resource, sys
from dataclasses import dataclass
import numpy as np
# The module alone, from its file, as a process that imports nothing else of ours.
spec = importlib.util.spec_from_file_location("allocator", sys.argv[2])
allocator = importlib.util.module_from_spec(spec)
spec.loader.exec_module(allocator)
applied = allocator.keep_freed_memory() if sys.argv[1] == "keep" else False
def once():
    blocks = [np.empty(1 << 20, dtype=np.float32) for _ in range(6)]
    for block in blocks:
        block.fill(1.0)
    del blocks
def measure(_config=None):
    once()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(50):
        once()
    after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    return {"applied": applied, "faults": after - before}
if sys.argv[1] == "door":  # the same as a command's main, run through the door
    from overtake.cli import Command
    @dataclass(frozen=True)
    class NoOptions:
        pass
    Command("overtake-probe", NoOptions, measure, report=lambda c, r: print(json.dumps(r))).run([])
else:
    print(json.dumps(measure()))
"""


def _faults(mode: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    clean.pop("GLIBC_TUNABLES", None)
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode, allocator.__file__],
        env={**clean, **env},
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    ).stdout
    return json.loads(out)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_blocks_are_reused_instead_of_faulted_in_again() -> None:
    default = _faults("default")
    kept = _faults("keep")
    assert kept["applied"] is True
    # 300 blocks of 1,024 pages: glibc's default gives the heap's top back after each round
    # (24 MiB free there, past its trim threshold of twice the largest block) and faults it
    # in again; kept, the blocks are reused.
    assert default["faults"] > 50_000, default
    assert kept["faults"] < default["faults"] / 20, (kept, default)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_every_command_keeps_freed_memory_through_its_door() -> None:
    default = _faults("default")
    through_the_door = _faults("door")
    assert through_the_door["faults"] < default["faults"] / 20, (through_the_door, default)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_users_own_malloc_settings_are_left_alone() -> None:
    assert _faults("keep", MALLOC_TRIM_THRESHOLD_="131072")["applied"] is False
    assert _faults("keep", GLIBC_TUNABLES="glibc.malloc.trim_threshold=131072")["applied"] is False
    assert _faults("keep", GLIBC_TUNABLES="glibc.rtld.nns=4")["applied"] is True

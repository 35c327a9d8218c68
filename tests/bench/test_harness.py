"""The benchmarks' shared harness: what it cleans up after a run."""

from __future__ import annotations

import mmap

from bench.harness import zenoh_pools_removed


def test_zenoh_pools_left_by_a_run_go_and_those_in_use_or_older_stay(tmp_path):
    older = tmp_path / "1.zenoh"
    older.write_bytes(b"\0" * 4096)
    with zenoh_pools_removed(tmp_path):
        left = tmp_path / "2.zenoh"  # a pool whose process ended without cleaning up
        left.write_bytes(b"\0" * 4096)
        in_use = tmp_path / "3.zenoh"
        in_use.write_bytes(b"\0" * 4096)
        other = tmp_path / "notes.txt"
        other.write_text("not a pool")
        file = in_use.open("r+b")
        mapping = mmap.mmap(file.fileno(), 4096)  # still mapped by this process
    try:
        assert not left.exists()
        assert in_use.exists() and older.exists() and other.exists()
    finally:
        mapping.close()
        file.close()

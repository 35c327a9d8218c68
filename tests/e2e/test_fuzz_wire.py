"""Hostile frames on every key a server and a trainer listen on (bench/fuzz/fuzz_wire.py, briefly):
the server keeps answering and an honest trainer keeps stepping. The bench command sends
100,000 frames; its figures are in bench/RELIABILITY.md."""

from __future__ import annotations

import pytest

from bench.fuzz.fuzz_wire import TARGETS, FuzzConfig, main


@pytest.mark.slow  # 12 s of floods; the codec's own mutations are checked in the default suite
@pytest.mark.timeout(120)
def test_hostile_frames_on_every_key_harm_nobody(tmp_path):
    config = FuzzConfig(
        frames=1_500,
        check_every=500,
        seed=1,
        flood_puts=200_000,
        flood_queries=2_000,
        json=tmp_path / "fuzz.json",
    )
    result = main(config)
    assert result["failures"] == []
    # After a flood of 200,000 frames the server answers again (what it queued is bounded:
    # tests/e2e/test_remote_server.py::test_a_flood_queues_at_most_its_bound).
    assert result["flood"]["status_answered"]
    assert set(result["sent"]) == set(TARGETS) and min(result["sent"].values()) > 100
    # The honest trainer stepped all along, and the stranger's opens stayed within its limit.
    steps = [check["honest_steps"] for check in result["checks"]]
    assert steps == sorted(steps) and steps[-1] > steps[0]
    assert all(
        check["server_arenas_used"] <= 1 + FuzzConfig.max_arenas_per_trainer
        for check in result["checks"]
    )

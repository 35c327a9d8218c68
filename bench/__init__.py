"""overtake's benchmarks, by audience: ``speed`` (how fast, each figure a ratio to a peer
measured in the same run; bench/RESULTS.md), ``reliability`` (what holds for hours, under load
and faults; bench/RELIABILITY.md), ``fuzz`` (hostile input at the wire) and ``fidelity``
(behaving as the peers and papers do). ``harness`` and ``rates`` are what they share, ``peers``
the peer simulators measured. Not part of the overtake package: run them from the repository's
root, ``python -m bench.AUDIENCE.MODULE``.
"""

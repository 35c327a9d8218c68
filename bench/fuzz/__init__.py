"""Fuzz: for whoever exposes a server to a network, and asks what hostile input does to it.
Hypothesis-made frames at every key a live server and a trainer listen on while an honest
trainer steps (nothing may crash or stall it), and libFuzzer's mutations at the wire codec's
decoder (only the protocol's own errors may come out); bench/RELIABILITY.md keeps their runs.
"""

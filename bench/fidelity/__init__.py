"""Fidelity: for whoever asks whether overtake behaves as its peers and papers say, apart from
how fast. highway-env's scene driven side by side with overtake's preset of it by fixed
drivers, and a DQN trained on each driving the other; tables in the shape of Min et al.'s
Table III from training runs and their evaluations, for bench/RESULTS.md.
"""

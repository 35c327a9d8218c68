"""A sum tree over a fixed number of leaves: proportional sampling in O(log n) per draw, all
draws of a batch at once (Schaul et al. 2016, prioritized experience replay).

The leaves hold non-negative priorities; each inner node the sum of its two children, so the
root holds the total. A draw of ``u`` in [0, total) descends from the root, going left where
``u`` falls within the left child's sum and right (less that sum) otherwise, and ends at the
leaf whose span of the cumulative sum holds ``u``: leaf ``i`` is drawn with probability
``priority[i] / total``.
"""

from __future__ import annotations

import numpy as np


class SumTree:
    """``size`` leaves (priorities), in a flat array: node 1 the root, node ``k``'s children
    ``2k`` and ``2k + 1``, the leaves from ``self.base``."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"a sum tree needs at least one leaf, got {size}")
        self.size = size
        self.base = 1 << int(np.ceil(np.log2(max(size, 2))))
        self.nodes = np.zeros(2 * self.base, dtype=np.float64)

    @property
    def total(self) -> float:
        return float(self.nodes[1])

    @property
    def priorities(self) -> np.ndarray:
        """The leaves' priorities (a view)."""
        return self.nodes[self.base : self.base + self.size]

    def update(self, leaves: np.ndarray, priorities: np.ndarray) -> None:
        """Set ``leaves``' priorities (later entries win where a leaf repeats) and the sums
        above them."""
        leaves = np.asarray(leaves, dtype=np.int64)
        values = np.asarray(priorities, dtype=np.float64)
        if leaves.size == 0:
            return
        if np.any(values < 0) or not np.all(np.isfinite(values)):
            raise ValueError("priorities must be finite and >= 0")
        self.nodes[self.base + leaves] = values
        nodes = np.unique((self.base + leaves) // 2)
        while nodes.size and nodes[0] >= 1:
            self.nodes[nodes] = self.nodes[2 * nodes] + self.nodes[2 * nodes + 1]
            nodes = np.unique(nodes // 2)
            nodes = nodes[nodes >= 1]

    def find(self, u: np.ndarray) -> np.ndarray:
        """The leaves the draws ``u`` (each in [0, total)) fall on."""
        u = np.asarray(u, dtype=np.float64).copy()
        node = np.ones(u.shape, dtype=np.int64)
        while node[0] < self.base:
            left = 2 * node
            go_right = u >= self.nodes[left]
            u = np.where(go_right, u - self.nodes[left], u)
            node = np.where(go_right, left + 1, left)
        # Rounding can carry a draw at the very top onto an empty leaf past the last: the last
        # leaf with a priority is where it belongs.
        leaf = np.minimum(node - self.base, self.size - 1)
        empty = self.nodes[self.base + leaf] <= 0.0
        if empty.any():
            holding = np.flatnonzero(self.priorities > 0.0)
            if holding.size:
                before = np.maximum(np.searchsorted(holding, leaf, "right") - 1, 0)
                leaf = np.where(empty, holding[before], leaf)
        return leaf

    def sample(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """``count`` leaves, each drawn with probability its priority over the total."""
        if self.total <= 0.0:
            raise RuntimeError("every priority is 0: nothing to draw")
        return self.find(rng.random(count) * self.total)

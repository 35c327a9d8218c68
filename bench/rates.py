"""Throughput figures shared by every benchmark result."""

from __future__ import annotations


class Rates:
    """Rates of a timed run; the class using it has simulated, wall and CPU seconds."""

    simulated_seconds: float
    wall_seconds: float
    cpu_seconds: float

    @property
    def sim_seconds_per_wall_second(self) -> float:
        return self.simulated_seconds / self.wall_seconds

    @property
    def sim_seconds_per_cpu_second(self) -> float:
        return self.simulated_seconds / self.cpu_seconds

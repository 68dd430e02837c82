"""Speed from Hall edges and a capture timer (paper 000, section 4.1, Eq. 1, Fig. 8).

    n [rpm] = 60 * fc / (P * nc)                                     (Eq. 1 of paper 000)

P = position pulses per revolution = 3 Hall sensors x 2 edges x pole pairs (12 for the
4-pole machine), nc = capture-timer counts between two successive Hall edges, fc = timer
clock. The numba versions are used inside the batched inner loop.
"""
from __future__ import annotations

from numba import njit


def pulses_per_rev(pole_pairs: int) -> int:
    """P of Eq. 1: every Hall edge (3 sensors, rising and falling) per mechanical turn."""
    return 6 * int(pole_pairs)


@njit(cache=True, error_model="numpy")
def speed_rpm_from_counts(nc, timer_hz, pole_pairs):
    """Eq. 1 of paper 000; nc <= 0 -> 0 (no valid interval yet)."""
    if nc <= 0:
        return 0.0
    return 60.0 * timer_hz / (6.0 * pole_pairs * nc)


@njit(cache=True, error_model="numpy")
def speed_upper_bound_rpm(counts_since_edge, timer_hz, pole_pairs):
    """No edge for `counts_since_edge` counts -> the speed cannot exceed Eq. 1 of that count
    (lets the estimate fall to zero when the shaft stops instead of holding the last value)."""
    return speed_rpm_from_counts(counts_since_edge, timer_hz, pole_pairs)


class HallSpeedEstimator:
    """Plain-Python estimator for tools and tests (the inner loop uses the numba functions, with
    the same rule for lost edges: bldc_control.process_edge / C_EDGES_FROM)."""

    def __init__(self, timer_hz: float, pole_pairs: int):
        self.timer_hz = float(timer_hz)
        self.pole_pairs = int(pole_pairs)
        self.last_count = None
        self.nc = 0
        self.speed_rpm = 0.0
        self.edges_from_count = 0     # every edge from this capture count on is seen

    def edges_lost_before(self, count: int) -> None:
        """Edges before capture count ``count`` may have gone unseen (a realtime controller that
        skipped PlantStates): the next edge only starts an interval, and the speed holds until
        then. nc across unseen edges would span several intervals and put Eq. 1 at a fraction
        of the speed."""
        self.edges_from_count = max(self.edges_from_count, int(count))

    def edge(self, count: int) -> float:
        """Eq. 1 of paper 000 with nc = counts since the previous edge, when no edge between
        them can have been lost."""
        count = int(count)
        if (self.last_count is not None and count > self.last_count
                and self.last_count >= self.edges_from_count):
            self.nc = count - self.last_count
            self.speed_rpm = speed_rpm_from_counts(self.nc, self.timer_hz, self.pole_pairs)
        self.last_count = count
        return self.speed_rpm

"""Device clock (`t_ms`, Arduino `millis()`) to host time, without the USB jitter.

Plain Python, no ROS. The host sees each sample some time after the device took it:
`receive = acquisition + latency`, and the latency is one-sided (never negative) with a
long tail (USB polling, buffering, a busy host). So `receive - device_time` is the
clock offset plus a latency, and its *lower envelope* is the offset plus the smallest
latency. We track that envelope and stamp with it: the minimum of the observed offset
in blocks of `block_s` of device time, and the highest straight line under the block
minima of the last `window_s` on average (the slope is the drift of the device's resonator
against the host clock; blocks a faster fall shows were late are dropped). A stamp is
never later than the sample's receive time, and stamps only go forward while the host
clock does: when the envelope drops (the first lines came late) or lines read together
share a receive time, a stamp that would not follow the last one is put a nanosecond after
it (for lines read together, a few nanoseconds past their shared receive time).
docs/driver.md describes the method and its limits.
"""

from __future__ import annotations

import collections
import itertools
import math

from pma_common.protocol import U32

NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000


class ClockSync:
    """Maps device milliseconds to host nanoseconds; `reset()` when the device restarts."""

    def __init__(self, window_s: float = 10.0, block_s: float = 0.5,
                 max_drift_ppm: float = 20_000.0, jump_s: float = 1.0,
                 jump_confirm_s: float = 5.0):
        if not (block_s > 0 and window_s >= 2 * block_s):
            raise ValueError('need block_s > 0 and window_s >= 2 * block_s')
        self.window_s = window_s
        self.block_s = block_s
        self.max_drift = max_drift_ppm * 1e-6
        self.jump_s = jump_s
        self.jump_confirm_s = jump_confirm_s
        self.resets = 0
        # The last stamp and its receive time belong to the host clock, so they outlive a
        # reset: a restarted device's first stamp must still follow the last one published.
        self._last_stamp_ns: int | None = None
        self._last_receive_ns: int | None = None
        self.reset()
        self.resets = 0

    def reset(self) -> None:
        """Forget the device clock: it restarted (reconnect, Arduino reset)."""
        self._last_t_ms: int | None = None
        self._device_ms = 0          # unwrapped device clock [ms]
        self._ref_device_ns = 0      # origin of x (device time) for the line fit
        self._ref_offset_ns = 0      # origin of y (offset) for the line fit
        self._blocks: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=max(2, math.ceil(self.window_s / self.block_s)))
        self._block_start: float | None = None
        self._block_min: tuple[float, float] | None = None   # (x, y) of the block's minimum
        self._intercept = math.inf   # offset line: y = intercept + slope * x  [s]
        self._slope = 0.0
        self._late_since: float | None = None
        self.samples = 0
        self.resets += 1

    @property
    def offset_s(self) -> float:
        """Current host-minus-device offset estimate [s] (NaN before the first sample)."""
        if self.samples == 0:
            return math.nan
        x = (self._device_ms * NS_PER_MS - self._ref_device_ns) / NS_PER_S
        return (self._ref_offset_ns / NS_PER_S) + self._intercept + self._slope * x

    @property
    def drift_ppm(self) -> float:
        """Estimated rate of the device clock against the host clock [ppm]."""
        return self._slope * 1e6

    def unwrap(self, t_ms: int) -> int | None:
        """Continuous device time [ms] across the 32-bit wrap; None when the clock went back."""
        if self._last_t_ms is None:
            return t_ms
        delta = (t_ms - self._last_t_ms) % U32
        if delta >= U32 // 2:
            return None
        return self._device_ms + delta

    def stamp(self, t_ms: int, receive_ns: int) -> int:
        """Acquisition time [ns, host clock] of a sample taken at device time `t_ms`.

        `receive_ns` is when the host read the sample's line (same clock as the result).
        """
        device_ms = self.unwrap(t_ms)
        if device_ms is None:  # device restarted without us noticing a reconnect
            self.reset()
            device_ms = t_ms
        if self.samples == 0:
            self._ref_device_ns = device_ms * NS_PER_MS
            self._ref_offset_ns = receive_ns - self._ref_device_ns
        self._last_t_ms = t_ms
        self._device_ms = device_ms
        device_ns = device_ms * NS_PER_MS
        x = (device_ns - self._ref_device_ns) / NS_PER_S
        y = (receive_ns - device_ns - self._ref_offset_ns) / NS_PER_S

        if self.samples > 0 and self._jumped(x, y):
            self.reset()
            return self.stamp(t_ms, receive_ns)
        self.samples += 1
        self._add_point(x, y)
        estimate_ns = device_ns + self._ref_offset_ns + round(
            (self._intercept + self._slope * x) * NS_PER_S)
        stamp_ns = min(estimate_ns, receive_ns)
        # In order, unless the host clock went back (then follow it).
        if self._last_stamp_ns is not None and receive_ns >= self._last_receive_ns:
            stamp_ns = max(stamp_ns, self._last_stamp_ns + 1)
        self._last_stamp_ns, self._last_receive_ns = stamp_ns, receive_ns
        return stamp_ns

    def _jumped(self, x: float, y: float) -> bool:
        """True when the host clock jumped (not latency): the estimate must start over."""
        residual = y - (self._intercept + self._slope * x)
        if residual < -self.jump_s:
            return True
        if residual > self.jump_s:
            # A stalled host also delivers late samples, but only for the stall's length.
            if self._late_since is None:
                self._late_since = x
            return x - self._late_since > self.jump_confirm_s
        self._late_since = None
        return False

    def _add_point(self, x: float, y: float) -> None:
        if self._block_start is None:
            self._block_start = x
        elif x - self._block_start >= self.block_s:
            self._blocks.append(self._block_min)
            self._block_start = x
            self._block_min = None
            self._fit()
        if self._block_min is None or y < self._block_min[1]:
            self._block_min = (x, y)
        # A new minimum below the line means the line was too high: lower it now.
        if math.isinf(self._intercept):
            self._intercept = y
        below = (self._intercept + self._slope * x) - y
        if below > 0:
            self._intercept -= below

    def _fit(self) -> None:
        """The offset line: the highest line under every block minimum at their mean time.

        That is the lower convex hull's edge over the mean (Moon, Skelly and Towsley, 1999:
        the linear program "below every point, as high as possible on average"), within the
        drift bound. A hull edge that falls faster than any clock drifts is latency that
        ended (the host read the first seconds late): the blocks before it were late, and are
        forgotten. A least-squares line through the minima let such blocks tilt it to the
        drift bound, and the stamps walked away from the samples by 20 ms a second until the
        late blocks left the window.
        """
        hull = _lower_hull(list(self._blocks))
        late_until = None
        for (x0, y0), (x1, y1) in itertools.pairwise(hull):
            if y1 - y0 < -self.max_drift * (x1 - x0):
                late_until = x1
        if late_until is not None:
            while self._blocks[0][0] < late_until:
                self._blocks.popleft()
            # The lower hull of the points from one of its vertices on is its rest.
            hull = [point for point in hull if point[0] >= late_until]
        points = list(self._blocks)
        if len(points) < 3:
            self._slope = 0.0
            self._intercept = min(p[1] for p in points)
            return
        mean_x = sum(p[0] for p in points) / len(points)
        slope = 0.0
        for (x0, y0), (x1, y1) in itertools.pairwise(hull):
            if x0 <= mean_x <= x1:
                slope = (y1 - y0) / (x1 - x0)
                break
        self._slope = max(-self.max_drift, min(self.max_drift, slope))
        self._intercept = min(y - self._slope * x for x, y in points)


def _lower_hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The lower convex hull of points in increasing x (Andrew's monotone chain)."""
    hull: list[tuple[float, float]] = []
    for point in points:
        while len(hull) >= 2:
            (x0, y0), (x1, y1) = hull[-2], hull[-1]
            # Drop the middle point unless it lies strictly below the chord to the new one.
            if (x1 - x0) * (point[1] - y0) - (y1 - y0) * (point[0] - x0) <= 0.0:
                hull.pop()
            else:
                break
        hull.append(point)
    return hull

"""ClockSync against a simulated device clock with one-sided USB latency."""

import numpy as np
import pytest

from pma_common.protocol import U32
from pma_driver.clock_sync import ClockSync

pytestmark = pytest.mark.in_process

MIN_LATENCY_S = 0.001


def simulate(rate_hz, duration_s, drift_ppm=0.0, *, seed=0, offset_s=1000.0, t0_ms=0):
    """Device sample times and host receive times: latency = 1 ms + exponential + rare spikes."""
    rng = np.random.default_rng(seed)
    n = int(rate_hz * duration_s)
    device_ms = t0_ms + np.round(np.arange(n) * 1000.0 / rate_hz).astype(np.int64)
    true_host_s = offset_s + (device_ms - t0_ms) / 1000.0 * (1.0 - drift_ppm * 1e-6)
    latency = MIN_LATENCY_S + rng.exponential(0.002, n)
    spikes = rng.random(n) < 0.02
    latency[spikes] += rng.uniform(0.01, 0.05, spikes.sum())
    receive_ns = np.round((true_host_s + latency) * 1e9).astype(np.int64)
    # Lines arrive in order: a late line delays the ones queued behind it.
    receive_ns = np.maximum.accumulate(receive_ns)
    return device_ms % U32, true_host_s, receive_ns


def stamp_errors(sync, device_ms, true_host_s, receive_ns):
    stamps = np.array([sync.stamp(int(t), int(r)) for t, r in zip(device_ms, receive_ns,
                                                                   strict=True)])
    return stamps / 1e9 - (true_host_s + MIN_LATENCY_S)


@pytest.mark.parametrize('rate_hz', [20.0, 1000.0])
@pytest.mark.parametrize('drift_ppm', [0.0, 500.0, -3000.0])
def test_stamps_have_far_less_jitter_than_receive_times(rate_hz, drift_ppm):
    device_ms, true_host_s, receive_ns = simulate(rate_hz, 30.0, drift_ppm)
    errors = stamp_errors(ClockSync(), device_ms, true_host_s, receive_ns)
    settled = errors[int(rate_hz * 3):]          # after the first few blocks
    receive_errors = receive_ns / 1e9 - (true_host_s + MIN_LATENCY_S)
    assert np.percentile(np.abs(receive_errors), 99) > 0.008
    assert np.percentile(np.abs(settled), 99) < 0.0015
    assert np.max(settled) <= 0.0015


def test_drift_is_estimated():
    sync = ClockSync()
    device_ms, true_host_s, receive_ns = simulate(50.0, 30.0, drift_ppm=1000.0)
    stamp_errors(sync, device_ms, true_host_s, receive_ns)
    assert sync.drift_ppm == pytest.approx(-1000.0, abs=150.0)


def test_stamp_never_after_receive_time():
    sync = ClockSync()
    device_ms, _, receive_ns = simulate(100.0, 10.0)
    for t, r in zip(device_ms, receive_ns, strict=True):
        assert sync.stamp(int(t), int(r)) <= r


def test_32_bit_wrap_of_device_clock_is_continuous():
    device_ms, true_host_s, receive_ns = simulate(100.0, 20.0, t0_ms=U32 - 5000)
    assert device_ms.min() < 1000 and device_ms.max() > U32 - 1000   # it does wrap
    errors = stamp_errors(ClockSync(), device_ms, true_host_s, receive_ns)
    assert np.percentile(np.abs(errors[300:]), 99) < 0.0015


def test_device_restart_resets_the_estimate():
    sync = ClockSync()
    device_ms, true_host_s, receive_ns = simulate(50.0, 10.0)
    stamp_errors(sync, device_ms, true_host_s, receive_ns)
    # The Arduino resets: its clock starts at 0 again, 10 s later in host time.
    device2, true2, receive2 = simulate(50.0, 10.0, offset_s=1020.0, seed=1)
    errors = stamp_errors(sync, device2, true2, receive2)
    assert sync.resets == 1
    assert np.percentile(np.abs(errors[150:]), 99) < 0.0015


def test_explicit_reset_forgets_the_old_offset():
    sync = ClockSync()
    sync.stamp(1000, 5_000_000_000)
    sync.reset()
    assert sync.samples == 0
    assert sync.stamp(1000, 9_000_000_000) == 9_000_000_000


def test_a_device_restart_read_with_the_last_lines_does_not_step_back():
    """The device's hello and first sample read in the same chunk as the previous device's
    last lines: the restart resets the estimate, but the stamps still go forward (one CI run
    saw a stamp a few nanoseconds before the last, with the simulated AVR)."""
    sync = ClockSync()
    chunk_ns = 7_000_000_000
    before = [sync.stamp(5_000 + 20 * i, chunk_ns) for i in range(3)]     # read together
    assert before[-1] > chunk_ns
    sync.reset()                                       # what the driver does on a hello
    after = sync.stamp(3, chunk_ns)
    assert after > before[-1]
    assert after - chunk_ns <= 10


def test_host_clock_jump_back_restarts_estimate():
    sync = ClockSync()
    device_ms, true_host_s, receive_ns = simulate(50.0, 5.0)
    stamp_errors(sync, device_ms, true_host_s, receive_ns)
    jumped = sync.stamp(int(device_ms[-1]) + 20, int(receive_ns[-1]) - 10 * 10**9)
    assert sync.resets == 1
    assert jumped <= int(receive_ns[-1]) - 10 * 10**9


def test_stamps_keep_increasing_when_lines_are_read_together():
    """A busy host (seen on a loaded CI machine with the simulated AVR) reads several lines in
    one read(), so they share a receive time, and the first ones come late. Consumers sort and
    difference the stamps: they must go forward, and stay at the receive time (ties are kept
    in order a nanosecond apart)."""
    sync = ClockSync()
    device_ms, _, receive_ns = simulate(20.0, 5.0)
    backlog = np.clip(0.3 - np.arange(device_ms.size) * 0.05, 0.0, None)   # 300 ms, draining
    chunk_ns = np.maximum.accumulate(receive_ns + np.round(backlog * 1e9).astype(np.int64))
    assert np.count_nonzero(np.diff(chunk_ns) == 0) >= 3                 # lines read together
    stamps = [sync.stamp(int(t), int(r)) for t, r in zip(device_ms, chunk_ns, strict=True)]
    assert np.all(np.diff(stamps) > 0)
    assert all(s <= r + 10 for s, r in zip(stamps, chunk_ns, strict=True))


def test_stamps_follow_the_host_clock_back():
    sync = ClockSync()
    first = sync.stamp(1000, 5_000_000_000)
    # Back by less than the jump threshold: no reset, and no stamp after the receive time.
    assert sync.stamp(1050, 4_600_000_000) <= 4_600_000_000 < first



@pytest.mark.parametrize('late_from_s', [0.0, 4.0])
def test_a_late_stretch_does_not_tilt_the_drift(late_from_s):
    """A busy host reads 2 s of lines 300 ms late (at the start, or later on), then drains
    its backlog a line a millisecond and reads on time again. The late blocks must not pass
    for drift: a least-squares line through the block minima took them for the 2 % bound,
    and the stamps walked 20 ms a second away from the samples for the rest of the window."""
    sync = ClockSync()
    device_ms = np.arange(0, 12_000, 50)
    true_ns = 1_000_000_000_000 + device_ms * 1_000_000
    late = (device_ms >= late_from_s * 1000) & (device_ms < late_from_s * 1000 + 2_000)
    receive_ns = true_ns + np.where(late, 300_000_000, 1_000_000)
    for i in range(1, receive_ns.size):      # in order: the backlog drains a line a ms
        receive_ns[i] = max(receive_ns[i], receive_ns[i - 1] + 1_000_000)
    stamps = np.array([sync.stamp(int(t), int(r))
                       for t, r in zip(device_ms, receive_ns, strict=True)])
    on_time = device_ms >= late_from_s * 1000 + 2_500
    errors_ms = (stamps - true_ns - 1_000_000)[on_time] / 1e6
    assert np.abs(errors_ms).max() < 0.5, errors_ms
    assert abs(sync.drift_ppm) < 100.0
    assert np.all(np.diff(stamps) > 0) and np.all(stamps <= receive_ns)

"""DeviceControl against the simulated device: who may command what, and tare."""

from __future__ import annotations

import math
import threading
import time

import pytest
from sim_link import SimClock, SimLink

from pma_common.calibration import PressureCalibration
from pma_driver.command_gate import DeviceControl
from pma_sim.device import DeviceConfig, SimDevice

pytestmark = pytest.mark.in_process

SENSOR = PressureCalibration()


@pytest.fixture
def control():
    device = SimDevice(DeviceConfig(rate_hz=50, seed=4))
    control = DeviceControl(400_000.0)
    link = SimLink(device, on_sample=lambda s: control.note_sample(s, SENSOR.adc_to_pa(s.adc)))
    control.link, control.active = link, True
    SimClock(link).sleep(0.2)       # some samples: a latest reading
    return control


@pytest.mark.parametrize(('value', 'kind', 'words'), [
    (math.nan, 'non-finite', 'setpoint nan is not a finite number'),
    (math.inf, 'non-finite', 'setpoint inf is not a finite number'),
    (-1.0, 'negative', 'setpoint -1 Pa is negative'),
    (400_001.0, 'too high', 'setpoint 400001 Pa is above max_gauge_pressure_pa 400000 Pa'),
])
def test_bad_setpoints_never_reach_the_device(control, value, kind, words):
    assert control.command_setpoint(value) == (kind, words + (' (gauge pressure)'
                                                              if kind == 'negative' else ''))
    assert control.link.commands('SET') == []


def test_the_ceiling_is_the_lower_of_the_parameter_and_the_device_limit(control):
    assert control.ceiling_pa() == 400_000
    control.max_gauge_pressure_pa = 900_000.0
    assert control.ceiling_pa() == 500_000          # HELLO's limit_pa


def test_nothing_is_commanded_while_inactive_or_with_the_link_closed(control):
    link = control.link
    control.deactivate()
    assert control.command_setpoint(100_000.0) == ('inactive', 'driver not active')
    assert link.commands('VENT') == [()]
    control.active, control.link = True, None
    assert control.command_setpoint(100_000.0) == ('link', 'link closed')
    assert link.commands('SET') == []


def test_tare_at_rest_returns_the_count_the_device_took_as_zero(control):
    adc, reason = control.tare()
    assert reason == '' and adc == control.link.device.tare_adc
    control.command_setpoint(150_000.0)
    SimClock(control.link).sleep(2.0)
    assert control.tare() == (None, 'the muscle is not vented: send setpoint 0.0 first and let '
                                    'the pressure settle')


def test_a_burst_of_setpoints_keeps_one_set_in_flight_and_the_newest_wins(control):
    """A controller at the sample rate, or `ros2 topic pub -r 1000`: the device gets the
    newest setpoint, never a backlog (the real firmware lost SETs sent ~28 at a time)."""
    link = control.link
    link.reply_delay_ms = 5                      # answers take a few ms, as on the wire
    before = len(link.commands('SET'))
    for value in range(100_000, 130_000, 1_000):      # 30 setpoints back to back
        assert control.command_setpoint(float(value)) == ('', '')
    assert len(link.commands('SET')) - before == 1   # the first; the rest wait, coalesced
    SimClock(link).sleep(0.1)
    sent = link.commands('SET')[before:]
    assert sent == [(100_000,), (129_000,)]          # then only the newest
    assert control.setpoints_coalesced == 28
    assert control.setpoints_sent == 2
    assert link.device.setpoint_pa == 129_000


def test_a_waiting_setpoint_does_not_overtake_a_deactivation(control):
    link = control.link
    link.reply_delay_ms = 5
    control.command_setpoint(100_000.0)
    control.command_setpoint(150_000.0)               # waits for the first SET's answer
    control.deactivate()                              # VENT now
    SimClock(link).sleep(0.1)
    assert link.commands('SET')[-1] == (100_000,)     # 150 kPa was never sent
    assert link.device.setpoint_pa == 0


class LockHolder:
    """Another thread that holds `control.lock` until told, then does `then` and lets go:
    a setpoint callback paused by the scheduler while it holds the lock, a tare, a sweep."""

    def __init__(self, control: DeviceControl, then=lambda: None):
        self.held, self.release = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._run, args=(control, then), daemon=True)
        self._thread.start()
        assert self.held.wait(5)

    def _run(self, control, then) -> None:
        with control.lock:
            self.held.set()
            self.release.wait(5)
            then()

    def let_go(self) -> None:
        self.release.set()
        self._thread.join(5)


def wait_for(predicate, what: str) -> None:
    deadline = time.monotonic() + 5.0
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


@pytest.mark.parametrize('newer', [None, 175_000.0])
def test_a_waiting_setpoint_is_sent_once_the_lock_is_free_not_dropped(control, newer):
    """At a SET's answer the lock was busy for more than 50 ms (a setpoint callback paused by
    a busy machine while it held it, a tare, a sweep's SET): the waiting setpoint, the
    stream's newest, was dropped and the device kept the one before. Now it goes as soon as
    the lock is free; a newer one that came meanwhile goes instead (`newer`)."""
    link = control.link
    events: list[str] = []
    control.on_event = lambda _level, message: events.append(message)
    link.reply_delay_ms = 5
    control.command_setpoint(100_000.0)
    control.command_setpoint(150_000.0)               # waits for the first SET's answer
    holder = LockHolder(control, then=lambda: newer and control.command_setpoint(newer))
    SimClock(link).sleep(0.01)                        # the answer, while the lock is held
    assert link.commands('SET')[-1] == (100_000,)     # nothing sent past the holder
    holder.let_go()
    last = round(newer or 150_000.0)
    wait_for(lambda: link.commands('SET')[-1] == (last,), f'SET {last} sent')
    SimClock(link).sleep(0.1)
    assert link.commands('SET')[-2:] == [(100_000,), (last,)]
    assert link.device.setpoint_pa == last
    assert (control.setpoints_sent, control.setpoints_coalesced) == (2, 1 if newer else 0)
    assert events == []
    control.command_setpoint(120_000.0)               # nothing left in flight: sent at once
    assert link.commands('SET')[-1] == (120_000,)


def test_a_waiting_setpoint_refused_once_the_lock_is_free_leaves_nothing_in_flight(control):
    link = control.link
    events: list[str] = []
    control.on_event = lambda _level, message: events.append(message)
    link.reply_delay_ms = 5
    control.command_setpoint(100_000.0)
    control.command_setpoint(150_000.0)
    holder = LockHolder(control, then=lambda: setattr(control, 'max_gauge_pressure_pa',
                                                      120_000.0))
    SimClock(link).sleep(0.01)
    holder.let_go()                                   # the ceiling fell under 150 kPa
    wait_for(lambda: events, 'the waiting setpoint refused')
    assert events == ['setpoint 150000 Pa dropped: setpoint 150000 Pa is above '
                      'max_gauge_pressure_pa 120000 Pa']
    assert link.commands('SET')[-1] == (100_000,)
    control.command_setpoint(110_000.0)               # sent at once: nothing stuck in flight
    assert link.commands('SET')[-1] == (110_000,)


@pytest.fixture
def leased(control):
    """The control fixture with a simulated clock for leases, and a commander holding 200 kPa."""
    clock = SimClock(control.link)
    control.clock = clock
    control.leases.timeout_s = 1.0
    control.note_lease('lease-1', 'length_controller', True)
    assert control.command_setpoint(200_000.0) == ('', '')
    clock.sleep(0.5)
    return control, clock


def test_a_commander_lost_vents_the_muscle(leased):
    control, clock = leased
    control.note_lease('lease-1', 'length_controller', True)
    clock.sleep(0.9)
    assert control.check_leases() == []                     # renewed 0.9 s ago
    clock.sleep(0.2)
    events = control.check_leases()
    assert events == ['commander length_controller lost: no renewal of its lease for 1 s '
                      '(network down, or its host stopped); vented']
    assert control.link.commands('VENT') == [()] and control.commanders_lost == 1
    clock.sleep(2.0)
    assert control.link.device.setpoint_pa == 0 and control.link.device.rig.pressure_pa < 20_000


def test_hold_keeps_the_pressure_when_the_commander_is_lost(leased):
    control, clock = leased
    control.commander_lost_action = 'hold'
    clock.sleep(1.0)
    assert control.check_leases()[0].endswith('holding the pressure (commander_lost_action hold)')
    assert control.link.commands('VENT') == []
    clock.sleep(1.0)
    assert control.link.device.setpoint_pa == 200_000


def test_a_lost_commander_still_renewing_cannot_re_pressurise(leased):
    control, clock = leased
    clock.sleep(1.0)
    control.check_leases()
    assert not control.note_lease('lease-1', 'length_controller', True)   # the link is back
    kind, reason = control.command_setpoint(200_000.0)
    assert kind == 'lease' and 'length_controller lost the muscle' in reason
    assert control.link.commands('SET') == [(200_000,)]                   # the first only
    control.note_lease('lease-1', 'length_controller', False)            # it let go
    assert control.command_setpoint(100_000.0) == ('', '')


def test_an_idle_rig_set_once_keeps_its_pressure(control):
    """`pma set` holds no lease: a rig set once and left alone is never vented for it."""
    clock = SimClock(control.link)
    control.clock = clock
    control.command_setpoint(150_000.0)
    clock.sleep(5.0)
    assert control.check_leases() == [] and control.link.commands('VENT') == []

"""The one gate for commands that move air: setpoints, sweep steps, tare and vent; and what
happens when a remote commander is lost (commander_lease).

Plain Python, no ROS: the driver node and the SweepRunner share it, and its unit tests run
it against the simulated device. One lock is held from "may this pressure be commanded?" to
"sent", and by `deactivate` around "inactive + VENT", so no SET can overtake the VENT of a
deactivation. Nothing is ever sent above `ceiling_pa()`: the `max_gauge_pressure_pa`
parameter, never above the limit the device reported in its HELLO.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Protocol

from pma_common.driver_parameters import device_ceiling_pa
from pma_common.protocol import Ack, Command, Hello, Nak, Sample
from pma_common.setpoint import setpoint_refusal
from pma_driver.commander_lease import CommanderLeases
from pma_driver.link import LinkError, LinkState, Reply

_log = logging.getLogger('pma_driver.command_gate')


class Link(Protocol):
    """What DeviceControl needs of link.SerialLink (a test may put the simulated device here)."""

    @property
    def state(self) -> LinkState: ...

    @property
    def hello(self) -> Hello | None: ...

    @property
    def connected(self) -> bool: ...

    def send(self, command: Command, *args: int, timeout: float | None = None) -> Ack | Nak: ...

    def send_async(self, command: Command, *args: int,
                   on_reply: Callable[[Reply], None] | None = None) -> None: ...


class DeviceControl:
    """Who may command what, right now; and the latest reading to judge it by."""

    def __init__(self, max_gauge_pressure_pa: float,
                 on_event: Callable[[int, str], None] = _log.log, *,
                 commander_timeout_s: float = 0.8, commander_lost_action: str = 'vent',
                 clock: Callable[[], float] = time.monotonic):
        self.lock = threading.RLock()
        self.link: Link | None = None            # set at configure, None after cleanup
        self.active = False                      # the lifecycle node is active
        self.max_gauge_pressure_pa = max_gauge_pressure_pa
        self.latest: Sample | None = None
        self.latest_gauge_pa = math.nan
        # (sample, gauge Pa) in one object, replaced at every sample: a sweep tells a new
        # reading from one it has seen by identity, and never pairs a sample with another's Pa.
        self.latest_reading: tuple[Sample, float] | None = None
        self.on_event = on_event
        self._sweep_lock = threading.Lock()
        self._sweep_running = False
        # One SET in flight at a time; setpoints that come meanwhile replace each other and
        # the newest goes when the device has answered. A stream of setpoints (a controller
        # at the sample rate, `ros2 topic pub -r 1000`) then never overruns the firmware's
        # serial buffer: the real image lost commands from ~28 sent back to back.
        # `_set_state` guards the two fields and is never held while waiting: the link thread
        # settles them at an answer without `lock`, which a tare holds until that thread
        # brings TARE's answer. Only `command_setpoint`, holding `lock`, makes `_next_set`
        # a setpoint, and only while a SET is in flight.
        self._set_state = threading.Lock()
        self._set_in_flight = False
        self._next_set: int | None = None
        self.setpoints_sent = 0                  # SETs sent for pma/pressure_setpoint
        self.setpoints_coalesced = 0             # ... replaced by a newer one while waiting
        # Remote commanders' leases (renewed from a ROS callback, checked on a timer).
        self.clock = clock
        self.leases = CommanderLeases(commander_timeout_s)
        self.commander_lost_action = commander_lost_action
        self._lease_lock = threading.Lock()
        self.last_commander_lost = ''            # who was lost last, and why we think so
        # The last check came late with a lease held, so it judged nobody (CommanderLeases).
        self.lease_check_held_up = False

    # -- state ---------------------------------------------------------------------------

    def ceiling_pa(self) -> int:
        """The most any command may ask for now (the parameter may be lowered at any time)."""
        link = self.link
        return device_ceiling_pa(self.max_gauge_pressure_pa,
                                 link.hello if link is not None else None)

    def note_sample(self, sample: Sample, gauge_pa: float) -> None:
        self.latest = sample
        self.latest_gauge_pa = gauge_pa
        self.latest_reading = (sample, gauge_pa)

    def streaming(self) -> bool:
        """Commands need a streaming link: a stalled one too means nobody can watch them."""
        link = self.link
        return link is not None and link.state is LinkState.STREAMING

    def link_text(self) -> str:
        link = self.link
        return f'link {link.state.value}' if link is not None else 'link closed'

    def not_commandable(self) -> tuple[str, str]:
        """(kind, reason) why nothing may be commanded now; ('', '') when it may."""
        if not self.active:
            return 'inactive', 'driver not active'
        if not self.streaming():
            return 'link', self.link_text()
        return '', ''

    @property
    def sweep_running(self) -> bool:
        return self._sweep_running

    def claim_sweep(self) -> bool:
        """Take the device for one sweep (False: another one has it)."""
        with self._sweep_lock:
            if self._sweep_running:
                return False
            self._sweep_running = True
            return True

    def release_sweep(self) -> None:
        with self._sweep_lock:
            self._sweep_running = False

    # -- commands ------------------------------------------------------------------------

    def setpoint_refusal(self, gauge_pa: float) -> tuple[str, str]:
        """(kind, reason) why this setpoint must not reach the device; ('', '') when it may."""
        kind, reason = setpoint_refusal(gauge_pa, self.ceiling_pa())     # `pma set`'s too
        if reason:
            return kind, reason
        kind, reason = self.not_commandable()
        if reason:
            return kind, reason
        if self._sweep_running:
            return 'sweep', 'a sweep is running'
        with self._lease_lock:
            reason = self.leases.setpoint_refusal(self.clock())
        if reason:
            return 'lease', reason
        return '', ''

    def command_setpoint(self, gauge_pa: float) -> tuple[str, str]:
        """Send SET unless refused; (kind, reason) of the refusal, ('', '') when taken.

        Taken means sent now, or, while an earlier SET awaits its answer, sent right after it
        (replacing any other setpoint still waiting): the newest setpoint always wins.
        """
        with self.lock:
            kind, reason = self.setpoint_refusal(gauge_pa)
            if not reason:
                with self._set_state:
                    waits = self._set_in_flight
                    if waits:
                        if self._next_set is not None:
                            self.setpoints_coalesced += 1
                        self._next_set = round(gauge_pa)
                    self._set_in_flight = True
                if not waits:
                    self._send_set(round(gauge_pa))
        return kind, reason

    def _send_set(self, gauge_pa: int) -> None:
        """Send a setpoint's SET; `lock` is held and a SET marked in flight, this one."""
        if self.send(Command.SET, gauge_pa, on_answer=self._on_set_answered):
            self.setpoints_sent += 1
        else:
            with self._set_state:
                self._set_in_flight = False

    def _on_set_answered(self) -> None:
        """The device answered a SET (or never will): the waiting one goes, if still allowed.

        Runs on the link thread, which must never wait long for the lock: a tare holds it
        until this thread brings TARE's answer, a sweep while its SET is answered. So when
        the lock stays busy, the waiting setpoint goes from a thread of its own once the
        lock is free. It was once dropped instead: a setpoint callback that held the lock
        (briefly, but paused by a busy machine) for 50 ms lost the stream's newest setpoint.
        """
        with self._set_state:
            if self._next_set is None:
                self._set_in_flight = False
                return
        # Still marked in flight: setpoints coming meanwhile wait behind the waiting one.
        if self.lock.acquire(timeout=0.05):
            try:
                self._send_waiting()
            finally:
                self.lock.release()
        else:
            threading.Thread(target=self._send_waiting_when_free, daemon=True,
                             name='pma-setpoint').start()

    def _send_waiting_when_free(self) -> None:
        with self.lock:
            self._send_waiting()

    def _send_waiting(self) -> None:
        """Send the newest waiting setpoint, if still allowed; `lock` is held."""
        with self._set_state:
            waiting, self._next_set = self._next_set, None
            if waiting is None:              # cannot happen: only this answer's path takes it
                self._set_in_flight = False
                return
        _, reason = self.setpoint_refusal(float(waiting))
        if reason:       # deactivated, a sweep took over, the ceiling fell meanwhile
            with self._set_state:
                self._set_in_flight = False
            self.on_event(logging.WARNING, f'setpoint {waiting} Pa dropped: {reason}')
            return
        self._send_set(waiting)

    def send(self, command: Command, *args: int,
             on_answer: Callable[[], None] | None = None) -> bool:
        """Send without blocking; a NAK, a lost reply or an unsendable command is reported.

        `on_answer` runs once the device answered (ACK or NAK) or the answer timed out.
        """
        link = self.link
        if link is None or not link.connected:
            self.on_event(logging.WARNING, f'{command.value} {args} not sent: '
                          f'{self.link_text()}')
            return False

        def on_reply(reply: Reply) -> None:
            if not isinstance(reply, Ack):
                what = 'no reply' if reply is None else f'NAK {reply.reason}'
                self.on_event(logging.ERROR, f'device refused {command.value} {args}: {what}')
            if on_answer is not None:
                on_answer()

        try:
            link.send_async(command, *args, on_reply=on_reply)
        except LinkError as error:
            self.on_event(logging.WARNING, str(error))
            return False
        return True

    def send_and_wait(self, command: Command, *args: int) -> Ack | Nak:
        """Send and wait for the ACK or NAK (LinkError: none, or no link)."""
        link = self.link
        if link is None:
            raise LinkError(f'{command.value} not sent: link closed')
        return link.send(command, *args)

    def vent(self, why: str) -> bool:
        link = self.link
        if link is not None and link.connected and self.send(Command.VENT):
            self.on_event(logging.INFO, f'vented ({why})')
            return True
        return False

    # -- commander leases ----------------------------------------------------------------

    def note_lease(self, lease_id: str, commander: str, holding: bool) -> bool:
        """A pma/commander_lease message; False when it renews a lease already lost."""
        with self._lease_lock:
            return self.leases.renew(lease_id, commander, holding, self.clock())

    def check_leases(self) -> list[str]:
        """Find the commanders lost since the last check and act (commander_lost_action):
        vent, or hold the pressure; a running sweep aborts either way (it sees lost_count
        rise). What happened, one line per commander."""
        with self._lease_lock:
            lost = self.leases.expired(self.clock())
            self.lease_check_held_up = (self.leases.last_check_skipped
                                        and bool(self.leases.holders()))
            whats = [f'commander {lease.commander} lost: no renewal of its lease for '
                     f'{self.leases.timeout_s:g} s (network down, or its host stopped)'
                     for lease in lost]
            if lost:   # with the count, under the lock: a sweep that sees the count rise
                self.last_commander_lost = '; '.join(whats)   # reads these, not the last
        events = []
        for what, lease in zip(whats, lost, strict=True):
            if self.commander_lost_action == 'hold':
                done = 'holding the pressure (commander_lost_action hold)'
            else:
                with self.lock:
                    done = ('vented' if self.vent(f'commander {lease.commander} lost')
                            else 'could not vent: ' + self.link_text())
            events.append(f'{what}; {done}')
        return events

    @property
    def commanders_lost(self) -> int:
        """How many leases have run out since start: a sweep notes it, and aborts on a rise
        (then last_commander_lost says who, set under the same lock)."""
        with self._lease_lock:
            return self.leases.lost_count

    def deactivate(self, why: str = 'deactivated') -> None:
        """Stop taking commands and vent, with no SET in between."""
        with self.lock:
            self.active = False
            self.vent(why)

    def tare(self) -> tuple[int | None, str]:
        """Zero the reading at rest: (the ADC count the device took as 0 Pa, '') or (None, why)."""
        with self.lock:
            _, reason = self.not_commandable()
            if reason:
                return None, f'{reason}: nothing to tare'
            if self._sweep_running:
                return None, 'a sweep is running'
            latest = self.latest
            if latest is None or latest.setpoint_pa != 0:
                return None, ('the muscle is not vented: send setpoint 0.0 first and let the '
                              'pressure settle')
            try:
                reply = self.send_and_wait(Command.TARE)   # held: cleanup takes the lock too
            except LinkError as error:
                return None, str(error)
        if not isinstance(reply, Ack) or reply.value is None:
            return None, (f'device refused TARE: {getattr(reply, "reason", reply)} (the reading '
                          'is not within 25 kPa of zero or outside the sensor span)')
        return reply.value, ''

"""fake_arduino: the simulated rig behind a pseudo-terminal, speaking protocol v1.

Prints `fake_arduino: device at /dev/pts/N` on stdout (again after every simulated
reconnect), and `fake_arduino: stats sent=... echo_timeouts=...` (see `LinkStats`) when it
closes its pty for a simulated unplug and when it exits; everything else is logged to
stderr. The device clock follows time.monotonic since (re)boot; the physics runs at 1 ms
steps in between.

Like a real USB-serial adapter, output is dropped while no host has the port open
or while the host does not read (the master is non-blocking), and bytes left unread
when the host closes the port are discarded when it opens again.
"""

from __future__ import annotations

import argparse
import collections
import csv
import dataclasses
import errno
import logging
import os
import select
import sys
import termios
import time
import tty
from collections.abc import Callable
from pathlib import Path

from pma_common import protocol
from pma_common.protocol import Valve
from pma_common.stop import StopRequest, stop_request
from pma_sim import registry
from pma_sim.device import (
    COMPILED_CEILING_PA,
    DeviceConfig,
    LinkFaultConfig,
    LinkFaults,
    Rig,
    SimDevice,
)
from pma_sim.registry import DEFAULT_FAMILY, DRIFT_SUFFIX

log = logging.getLogger('fake_arduino')

SPLIT_PAUSE_S = 0.02         # gap between the two halves of a split line
OUTBOX_LIMIT_BYTES = 4096    # like the adapter's buffer: beyond it, new lines are dropped
READ_CHUNK = 4096
IDLE_POLL_S = 0.05           # how often presence is re-checked while no host is attached
BLOCKED_RETRY_S = 0.005      # retry period while the host has the port open but does not read
# After a host opens the port, output waits this long (a real board is still in its bootloader
# then): a host that flushes its input right after opening, as the driver does, loses nothing.
ATTACH_SETTLE_S = 0.05


MAX_WAIT_S = 0.1             # longest sleep, so a stop request is seen promptly
# The most device time run in one pass of the loop, between which the host's waiting bytes
# are handed over and the device's output goes out. A simulator behind the wall clock (simavr
# on a loaded machine) would otherwise run seconds of firmware in one go, without the
# heartbeats the host sent meanwhile (it vented as no board would) and without a word out
# (the driver saw the link stall).
MAX_ADVANCE_MS = 50
# Said when the device runs this far behind the wall clock, and when it has caught up.
LAG_WARNING_MS = 500
# A loop pass this much longer than MAX_WAIT_S: this process was not scheduled, or the device
# simulates slower than real time. A process away longer than the heartbeat timeout hands
# the device the host's bytes of the gap at its start only, so it vents as a real board
# never would. Said, so that a test's log shows a simulator that could not keep up.
UNSCHEDULED_WARNING_S = 0.5


class _ListMuscles(argparse.Action):
    """--list-muscles: like --help, it prints and exits before other options are checked."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(registry.describe(), flush=True)
        parser.exit(0)


def parse_args(argv: list[str] | None = None, prog: str = 'fake_arduino',
               description: str = 'Simulated PMA rig on a pseudo-terminal (protocol v1).',
               extend: Callable[[argparse.ArgumentParser], None] | None = None,
               ) -> argparse.Namespace:
    """fake_arduino's options; simavr_arduino `extend`s them with its own."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add = parser.add_argument
    add('--link', type=Path, help='also make this path a symlink to the device (removed on exit)')
    add('--rate', type=int, default=20, help='sample rate at boot [Hz] (default 20, max 1000)')
    add('--max-rate', type=int, default=1000, help='max_rate_hz reported in HELLO (default 1000)')
    add('--ceiling-pa', type=int, default=COMPILED_CEILING_PA,
        help=f'pressure ceiling at boot [Pa] (default and limit {COMPILED_CEILING_PA})')
    add('--hb-timeout-ms', type=int, default=1000, help='heartbeat timeout at boot [ms]')
    add('--no-heartbeat-check', action='store_true',
        help='never vent on heartbeat loss (manual play only)')
    add('--seed', type=int, default=0, help='seed for sensor noise and faults (default 0)')
    add('--muscle', default=DEFAULT_FAMILY, metavar='FAMILY[+drift]',
        help=f'simulated muscle family, any of --list-muscles (default {DEFAULT_FAMILY}); '
        f'append {DRIFT_SUFFIX} for one whose rest length and stroke drift as it warms up '
        '(docs/simulated-rig.md)')
    add('--list-muscles', action=_ListMuscles,
        help='print every muscle family, one a line (what it models, its Table 1 fit), and exit')
    add('--echo-timeout-rate', type=float, default=0.0, help='share of samples without echo')
    add('--garbage-rate', type=float, default=0.0, help='share of lines preceded by garbage')
    add('--bad-checksum-rate', type=float, default=0.0, help='share of lines with a bad checksum')
    add('--drop-rate', type=float, default=0.0, help='share of lines silently dropped')
    add('--split-rate', type=float, default=0.0,
        help=f'share of lines written in two parts {SPLIT_PAUSE_S * 1000:.0f} ms apart')
    add('--stall-after', type=float, help='stop sending after this many seconds')
    add('--stall-for', type=float, default=2.0, help='length of the stall [s] (default 2)')
    add('--disconnect-after', type=float, help='close the pty (unplug) after this many seconds')
    add('--reconnect-after', type=float, default=2.0,
        help='new pty (device reboots) this many seconds after the unplug (default 2)')
    add('--truth', type=Path, metavar='CSV',
        help='write the simulated true length of every sample here (seq, device time, true '
             'length, true pressure): for evaluating a controller; nothing on ROS sees it')
    add('--log-level', default='INFO', choices=['DEBUG', 'INFO', 'WARNING', 'ERROR'])
    if extend is not None:
        extend(parser)
    args = parser.parse_args(argv)
    for name in ('stall_after', 'stall_for', 'disconnect_after', 'reconnect_after'):
        value = getattr(args, name)
        if value is not None and value < 0:
            parser.error(f'--{name.replace("_", "-")} must be >= 0')
    return args


class PtyPort:
    """The device end of a pseudo-terminal: the master fd, non-blocking, slave in raw mode."""

    def __init__(self):
        self.master, slave = os.openpty()
        self.path = os.ttyname(slave)
        tty.setraw(slave)          # no '\n' -> '\r\n', no echo, no line editing
        os.close(slave)            # the host opens it; a closed slave shows as POLLHUP
        os.set_blocking(self.master, False)
        self._poll = select.poll()
        self._poll.register(self.master, select.POLLIN)
        self.host_attached = False

    def check_host(self) -> bool:
        """True while some process has the slave open; flushes stale output on attach."""
        events = dict(self._poll.poll(0)).get(self.master, 0)
        attached = not events & select.POLLHUP
        if attached and not self.host_attached:
            # A fresh open sees only what is written from now on, like a USB adapter.
            termios.tcflush(self.master, termios.TCOFLUSH)
        self.host_attached = attached
        return attached

    def wait_readable(self, timeout_s: float) -> bool:
        if not self.host_attached:
            # What a host wrote just before it closed was on the wire: a board's UART
            # receives it (a driver's last VENT). It is read until the buffer is empty.
            if dict(self._poll.poll(0)).get(self.master, 0) & select.POLLIN:
                return True
            time.sleep(min(max(0.0, timeout_s), IDLE_POLL_S))
            return False
        events = dict(self._poll.poll(max(0.0, timeout_s) * 1000.0)).get(self.master, 0)
        return bool(events & select.POLLIN)

    def read(self) -> bytes:
        try:
            return os.read(self.master, READ_CHUNK)
        except BlockingIOError:
            return b''
        except OSError as error:
            if error.errno == errno.EIO:   # the host closed the slave meanwhile
                return b''
            raise

    def write(self, data: bytes) -> int:
        """Bytes accepted (maybe fewer than given; 0 when the buffer is full)."""
        try:
            return os.write(self.master, data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError as error:
            if error.errno == errno.EIO:
                return 0
            raise

    def close(self) -> None:
        os.close(self.master)


class Link:
    """A --link symlink that always points at the current pty (atomically replaced)."""

    def __init__(self, path: Path | None):
        self.path = path
        self.target: str | None = None
        if path is not None and path.exists() and not path.is_symlink():
            raise SystemExit(f'fake_arduino: --link {path} exists and is not a symlink')

    def point_at(self, target: str) -> None:
        if self.path is None:
            return
        temporary = self.path.with_name(f'.{self.path.name}.{os.getpid()}.tmp')
        temporary.unlink(missing_ok=True)
        os.symlink(target, temporary)
        os.replace(temporary, self.path)
        self.target = target

    def remove(self) -> None:
        if self.path is None or self.target is None:
            return
        try:
            if os.readlink(self.path) == self.target:
                self.path.unlink()
        except OSError:
            pass
        self.target = None


@dataclasses.dataclass
class LinkStats:
    """What reached the pty, line by line, since start (docs/simulated-rig.md).

    A line counts once the pty has taken its last byte (a split line: its second half).
    `sent`: sample lines written whole with a valid checksum: a host that reads everything
    decodes exactly these. `bad_checksum`, `garbage`, `split`: lines of any type written
    with that fault (a garbage run is a line of its own before an intact line). `dropped`:
    lines of any type the --drop-rate fault removed while a host had the port open (outside
    stalls). `echo_timeouts`: the `sent` samples with echo_us = 0.
    """

    sent: int = 0
    bad_checksum: int = 0
    garbage: int = 0
    dropped: int = 0
    split: int = 0
    echo_timeouts: int = 0

    def text(self, prog: str = 'fake_arduino') -> str:
        fields = ' '.join(f'{name}={value}' for name, value in dataclasses.asdict(self).items())
        return f'{prog}: stats {fields}'

    def count_written(self, line: _LineRecord) -> None:
        for fault in ('bad_checksum', 'garbage', 'split'):
            if fault in line.faults:
                setattr(self, fault, getattr(self, fault) + 1)
        if line.sample is not None and 'bad_checksum' not in line.faults:
            self.sent += 1
            self.echo_timeouts += line.sample.echo_us == 0


@dataclasses.dataclass(frozen=True)
class _LineRecord:
    faults: frozenset[str]
    sample: protocol.Sample | None


@dataclasses.dataclass
class _Chunk:
    due: float
    data: bytes
    line: _LineRecord | None   # on a line's last chunk: counted when it is written
    last: bool                 # the last chunk of its line


def describe_line(line: bytes, faults: frozenset[str]) -> _LineRecord:
    try:
        frame = protocol.parse_device_line(line.rstrip(b'\n'))
    except protocol.FrameError:
        frame = None
    return _LineRecord(faults, frame if isinstance(frame, protocol.Sample) else None)


class Writer:
    """Queued chunks with not-before times (split lines); writes what the pty accepts.

    Counts each line in `stats` when the pty takes its last byte.
    """

    def __init__(self, stats: LinkStats):
        self._queue: collections.deque[_Chunk] = collections.deque()
        self._hold_until = 0.0
        self.stats = stats
        self.dropped_lines = 0

    def queued_bytes(self) -> int:
        return sum(len(chunk.data) for chunk in self._queue)

    def push(self, chunks: list[bytes], now: float, line: _LineRecord | None = None) -> None:
        if not chunks:
            return
        if self.queued_bytes() > OUTBOX_LIMIT_BYTES:
            self.dropped_lines += 1
            return
        due = max(now, self._hold_until)
        for index, chunk in enumerate(chunks):
            if index:
                due += SPLIT_PAUSE_S
            last = index == len(chunks) - 1
            self._queue.append(_Chunk(due, chunk, line if last else None, last))

    def clear(self) -> None:
        self._queue.clear()

    def hold(self, until: float) -> None:
        """Write nothing before `until` (lines pushed meanwhile wait for it)."""
        self._hold_until = until

    def next_due(self) -> float | None:
        return self._queue[0].due if self._queue else None

    def flush(self, port: PtyPort, now: float) -> bool:
        """Write every chunk that is due; True while a partly written chunk waits for room.

        A chunk the pty takes nothing of is lost with the rest of its line (the host is not
        reading), like bytes a USB-serial adapter drops, so fresh output goes through once
        the host reads again. Lines are only cut short that way, while the host is not
        reading; a host that keeps reading gets every line whole.
        """
        while self._queue and self._queue[0].due <= now:
            head = self._queue[0]
            written = port.write(head.data)
            if 0 < written < len(head.data):
                head.data = head.data[written:]
                return True
            self._queue.popleft()
            if written:
                if head.last and head.line is not None:
                    self.stats.count_written(head.line)
                continue
            self.dropped_lines += 1
            while not head.last:      # the rest of the line (a split line's second half)
                head = self._queue.popleft()
        return False


def configs_from_args(args: argparse.Namespace) -> tuple[DeviceConfig, LinkFaultConfig]:
    """Raises ValueError with a readable message for out-of-range options."""
    device = DeviceConfig(
        rate_hz=args.rate, max_rate_hz=args.max_rate, ceiling_pa=args.ceiling_pa,
        hb_timeout_ms=args.hb_timeout_ms, heartbeat_check=not args.no_heartbeat_check,
        echo_timeout_rate=args.echo_timeout_rate, seed=args.seed, muscle=args.muscle)
    link = LinkFaultConfig(
        garbage_rate=args.garbage_rate, bad_checksum_rate=args.bad_checksum_rate,
        drop_rate=args.drop_rate, split_rate=args.split_rate)
    return device, link


class TruthLog:
    """The simulated truth beside each sample, as CSV (joined to pma/state by `seq`)."""

    HEADER = 'seq,device_time_s,true_length_m,true_gauge_pressure_pa\n'

    def __init__(self, path: Path):
        self._file = open(path, 'w', encoding='utf-8', buffering=1)
        self._file.write(self.HEADER)

    def write(self, sample: protocol.Sample, rig: Rig) -> None:
        self._file.write(f'{sample.seq},{sample.t_ms / 1000:.3f},{rig.length_m:.7f},'
                         f'{rig.pressure_pa:.1f}\n')

    def close(self) -> None:
        self._file.close()

    @staticmethod
    def true_lengths(path: Path) -> dict[int, float]:
        """seq -> the simulated true length [m], read back from a log this class wrote."""
        with open(path, newline='', encoding='utf-8') as stream:
            return {int(row['seq']): float(row['true_length_m'])
                    for row in csv.DictReader(stream)}


def advance(device: SimDevice, port: PtyPort, t_ms: int) -> bool:
    """Run `device` toward `t_ms` by at most MAX_ADVANCE_MS and hand it what the host wrote;
    True while it is still behind. The loop emits the device's output between calls, so a
    device that simulates slower than real time answers late but keeps talking, as a slow
    board would: caught up in one go, it fell silent for seconds and the driver saw a stall.
    A device in time gets the bytes at `t_ms`; one behind gets them before it runs on (they
    are already waiting when its clock gets there)."""
    behind = device.t_ms + MAX_ADVANCE_MS < t_ms
    if behind:
        _hand_over(device, port)
    device.advance_to(min(t_ms, device.t_ms + MAX_ADVANCE_MS))
    if not behind:
        _hand_over(device, port)
    return device.t_ms < t_ms


def _hand_over(device: SimDevice, port: PtyPort) -> None:
    """Give the device what the host has written, if anything."""
    if port.wait_readable(0.0):
        data = port.read()
        if data:
            device.receive(data)


def run(args: argparse.Namespace, stop: StopRequest,
        make_device: Callable[[DeviceConfig, Rig], SimDevice] = SimDevice,
        prog: str = 'fake_arduino') -> int:
    """The pty, its faults and the device clock around the device `make_device` returns.

    simavr_arduino passes the real firmware on simavr, which offers SimDevice's interface.
    """
    config, fault_config = configs_from_args(args)
    faults = LinkFaults(fault_config, seed=args.seed)
    link = Link(args.link)
    rig = Rig(config)
    truth = TruthLog(args.truth) if args.truth else None
    device = make_device(config, rig)
    if truth is not None:
        device.on_sample = truth.write
    stats = LinkStats()
    writer = Writer(stats)
    start = time.monotonic()
    stall = (None if args.stall_after is None
             else (start + args.stall_after, start + args.stall_after + args.stall_for))
    unplug_at = None if args.disconnect_after is None else start + args.disconnect_after
    replug_at = unplugged_at = 0.0
    port: PtyPort | None = None

    def plug_in() -> PtyPort:
        new = PtyPort()
        link.point_at(new.path)
        print(f'{prog}: device at {new.path}', flush=True)
        log.info('device at %s%s; %d Hz, ceiling %d Pa, heartbeat %s, muscle %s', new.path,
                 f' (link {args.link})' if args.link else '', config.rate_hz, config.ceiling_pa,
                 f'{config.hb_timeout_ms} ms' if config.heartbeat_check else 'not checked',
                 config.muscle)
        return new

    port = plug_in()
    boot = time.monotonic()
    stalled = lagging = False
    last_pass = time.monotonic()
    try:
        while not stop.is_set():
            now = time.monotonic()
            if now - last_pass > MAX_WAIT_S + UNSCHEDULED_WARNING_S:
                log.warning('a pass of the device loop took %.2f s (this process not '
                            'scheduled, or the device simulating slower than real time)',
                            now - last_pass)
            last_pass = now
            if unplug_at is not None and now >= unplug_at:
                log.warning('simulated unplug: closing %s', port.path)
                link.remove()
                port.close()
                writer.clear()
                print(stats.text(prog), flush=True)
                port, unplug_at, unplugged_at = None, None, now
                replug_at = now + args.reconnect_after
                continue
            if port is None:
                if now < replug_at:
                    time.sleep(min(IDLE_POLL_S, replug_at - now))
                    continue
                # Unpowered meanwhile: valves closed, the muscle kept its air (slow leak).
                rig.step(now - unplugged_at, Valve.HOLD)
                port = plug_in()
                device.boot()
                boot = now
                log.info('device rebooted: seq and clock restart')

            now_ms = int((now - boot) * 1000)
            behind = advance(device, port, now_ms)
            if (now_ms - device.t_ms > LAG_WARNING_MS) != lagging:
                lagging = not lagging
                if lagging:
                    log.warning('the device runs %.1f s behind the wall clock (it simulates '
                                'slower than real time)', (now_ms - device.t_ms) / 1000)
                else:
                    log.warning('the device has caught up with the wall clock')
            in_stall = stall is not None and stall[0] <= now < stall[1]
            if in_stall != stalled:
                log.warning('simulated stall %s', 'begins' if in_stall else 'ends')
                stalled = in_stall
            was_attached = port.host_attached
            attached = port.check_host()
            if attached and not was_attached:
                # Output starts after a pause and with a newline: a host that drops its
                # first (partial) line after opening drops just that empty line.
                writer.clear()
                writer.hold(now + ATTACH_SETTLE_S)
                writer.push([b'\n'], now)
            for line in device.take_output():
                if attached and not in_stall:
                    faulted = faults.apply(line)
                    if faulted.chunks:
                        writer.push(faulted.chunks, now, describe_line(line, faulted.faults))
                    else:
                        stats.dropped += 1
            if not attached:
                writer.clear()
            blocked = writer.flush(port, now)

            next_sample = boot + device.next_sample_ms * 1e-3
            deadlines = [next_sample, now + BLOCKED_RETRY_S if blocked
                         else writer.next_due() or next_sample]
            deadlines += [t for t in (unplug_at, stall and stall[0], stall and stall[1])
                          if t is not None and t > now]
            wait = 0.0 if behind else min(min(deadlines) - time.monotonic(), MAX_WAIT_S)
            if port.wait_readable(wait):
                behind = advance(device, port, int((time.monotonic() - boot) * 1000))
        log.info('%s: shutting down', stop.reason)
    finally:
        link.remove()
        if port is not None:
            port.close()
        if writer.dropped_lines:
            log.info('%d lines dropped because the host did not read', writer.dropped_lines)
        if any(faults.counts.values()):
            log.info('faults injected: %s', faults.counts)
        if truth is not None:
            truth.close()
        print(stats.text(prog), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(stream=sys.stderr, level=args.log_level,
                        format='fake_arduino %(levelname)s: %(message)s')
    try:
        configs_from_args(args)
    except ValueError as error:
        print(f'fake_arduino: {error}', file=sys.stderr)
        return 2
    return run(args, stop_request())


if __name__ == '__main__':
    sys.exit(main())

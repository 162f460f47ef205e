"""simavr_arduino: the firmware's own image on a simulated ATmega2560, with the simulated rig.

fake_arduino re-implements the firmware in Python; this runs the firmware itself: the .elf
that `make firmware` builds for the Mega executes on simavr at 16 MHz (the C program
`pma_simavr`, pma_sim/simavr/), so 16-bit `int`, the 8 KiB of RAM, the Arduino
core's timers and interrupts, `pulseInLong` and the UART at its baud rate all behave as on the
board. Everything around the board is fake_arduino's: the pty, `--link`, the link faults, the
stalls and unplugs, and the rig (`sim.device.Rig`: pneumatics, muscle, sensor noise), so the
same commands work against either.

How the two halves share time: `pma_simavr` never reads a clock. fake_arduino's loop asks
`SimavrDevice.advance_to(t_ms)` for each millisecond of wall time since boot, and the device
runs the AVR up to that cycle (16 000 cycles a millisecond). On the way the firmware samples
the world, and each time the AVR stops and asks: an ADC conversion of the sensor's channel
gets the rig's pressure reading (`Rig.read_adc`, as volts on A0), the end of a trigger pulse
gets the echo width (`Rig.read_echo_us`, played back on the echo pin 0.45 ms later). Valve
pin changes come back stamped with their cycle, and the physics steps at 1 ms in that same
simulated time, as in fake_arduino. simavr runs 2.5-4 times faster than the board on one
core here, so the AVR keeps up with the wall clock and catches up after a stall. On a
loaded machine it can fall behind: the loop then runs it 50 ms at a time
(fake_arduino.advance), handing it what the host wrote and sending out what it wrote in
between, so the firmware never runs a second without the heartbeats the host did send, and
the host hears it answer late rather than not at all.

Prints what fake_arduino prints (`simavr_arduino: device at ...`, `simavr_arduino: stats
...`) and, at exit, `simavr_arduino: firmware ...` with what only the real image can tell:
its longest main-loop pass (busy: asleep between passes excluded), how much of the time it
idled asleep, its stack high-water mark and free RAM, UART overruns.
docs/hardware.md ("Firmware in the loop") has the measurements and the differences.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from pma_common.calibration import PressureCalibration
from pma_common.protocol import Valve
from pma_common.stop import StopRequest, stop_request
from pma_sim import fake_arduino
from pma_sim.device import ECHO_START_US, DeviceConfig, Rig

log = logging.getLogger('simavr_arduino')

PROG = 'simavr_arduino'
MCU = 'atmega2560'
CPU_HZ = 16_000_000
CYCLES_PER_MS = CPU_HZ // 1000
# The Mega 2560's port pins behind the sketch's PIN_* constants (Arduino's variants/mega
# pins_arduino.h; test_firmware_simavr.py checks both): D5 inlet, D6 exhaust, D9 trigger,
# D10 echo, A0 the pressure sensor.
WIRING = {'inlet': 'E3', 'exhaust': 'H3', 'trigger': 'H6', 'echo': 'B4'}
PRESSURE_ADC_CHANNEL = 0
# HC-SR04 (datasheet): a trigger pulse of at least 10 us starts a measurement; with nothing
# in range Echo stays high for about 38 ms, and triggers meanwhile are ignored.
MIN_TRIGGER_US = 10
NO_ECHO_US = 38_000
# The valve pin levels that open each valve (the sketch's *_OPEN_LEVEL: HIGH).
INLET_OPEN_LEVEL = 1
EXHAUST_OPEN_LEVEL = 1
# Options whose values are compiled into the firmware: the image decides, not the command line.
COMPILED = {'rate': 'it boots at DEFAULT_RATE_HZ; RATE (sample_rate_hz) sets another',
            'max_rate': 'MAX_RATE_HZ is compiled in',
            'ceiling_pa': 'it boots at CEILING_LIMIT_PA; MAX (max_gauge_pressure_pa) lowers it',
            'hb_timeout_ms': 'it boots at DEFAULT_HEARTBEAT_TIMEOUT_MS; HBTO sets another',
            'no_heartbeat_check': 'its heartbeat check is always on',
            'truth': "the image's samples are not read back by the physics: use fake_arduino"}


def default_build_dir() -> Path:
    """Where tools/firmware.sh puts the image and the simulator (`PMA_FIRMWARE_BUILD_DIR`)."""
    configured = os.environ.get('PMA_FIRMWARE_BUILD_DIR')
    if configured:
        return Path(configured)
    return Path(__file__).resolve().parents[2] / 'build' / 'firmware'


class FirmwareStoppedError(RuntimeError):
    """The simulated AVR crashed or halted, or the simulator process ended."""


@dataclasses.dataclass
class FirmwareStats:
    """What `pma_simavr` measured since the last reset (its `stats` answer)."""

    values: dict[str, int]

    @property
    def longest_loop_us(self) -> float:
        return self.values['loop_max_cycles'] * 1e6 / self.values['frequency']

    @property
    def window_longest_loop_us(self) -> float:
        return self.values['window_loop_max_cycles'] * 1e6 / self.values['frequency']

    @property
    def asleep_percent(self) -> float:
        """Share of the time the CPU idled asleep between passes of loop()."""
        return 100 * self.values['asleep_cycles'] / max(self.values['cycle'], 1)

    @property
    def stack_peak_bytes(self) -> int:
        return self.values['ramend'] - self.values['min_sp']

    @property
    def free_ram_bytes(self) -> int:
        """SRAM never touched: between the end of .bss (no heap in use) and the deepest stack."""
        return self.values['min_sp'] + 1 - self.values['data_end']

    def text(self) -> str:
        v = self.values
        return (f'{PROG}: firmware loops={v["loops"]} '
                f'longest_loop_us={self.longest_loop_us:.0f} '
                f'asleep_percent={self.asleep_percent:.0f} '
                f'stack_peak_bytes={self.stack_peak_bytes} free_ram_bytes={self.free_ram_bytes} '
                f'rx_bytes={v["rx_bytes"]} rx_overruns={v["rx_overruns"]} '
                f'rx_dropped={v["rx_dropped"]} tx_bytes={v["tx_bytes"]} '
                f'triggers_ignored={v["triggers_ignored"]} triggers_short={v["triggers_short"]}')


class FirmwareSimulator:
    """The `pma_simavr` child: runs the image cycle by cycle and asks for sensor readings.

    `on_adc(cycle)` returns the sensor's millivolts for a conversion starting then,
    `on_trigger(cycle)` the echo width in us (0: no echo) for a trigger pulse ending then,
    `on_valves(cycle, inlet, exhaust)` hears pin levels; cycles count from the last reset.
    """

    def __init__(self, simulator: Path, firmware: Path, on_adc, on_trigger, on_valves):
        for path, what in ((simulator, 'simulator'), (firmware, 'firmware image')):
            if not Path(path).is_file():
                raise FileNotFoundError(
                    f'no {what} at {path}: build both with `make firmware` (tools/firmware.sh)')
        argv = [str(simulator), '--mcu', MCU, '--frequency', str(CPU_HZ),
                *(arg for pin, port in WIRING.items() for arg in (f'--{pin}', port)),
                '--adc-channel', str(PRESSURE_ADC_CHANNEL),
                '--echo-delay-us', str(ECHO_START_US), '--no-echo-us', str(NO_ECHO_US),
                '--min-trigger-us', str(MIN_TRIGGER_US), str(firmware)]
        # Its own session: a Ctrl-C to our group is ours to handle; it ends when stdin closes.
        self._process = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         start_new_session=True)
        self._on_adc, self._on_trigger, self._on_valves = on_adc, on_trigger, on_valves
        self.output = bytearray()   # UART0 bytes not yet taken
        self.cycle = 0

    def _send(self, text: str) -> None:
        try:
            self._process.stdin.write(text.encode('ascii'))
            self._process.stdin.flush()
        except BrokenPipeError:
            raise self._stopped() from None

    def _stopped(self) -> FirmwareStoppedError:
        code = self._process.wait(5)
        return FirmwareStoppedError(f'pma_simavr ended (exit {code})')

    def _until_done(self) -> None:
        """Serve the simulator's questions and events until it says `done`."""
        self.cycle = int(self._serve_until(b'done'))

    def _serve_until(self, answer: bytes) -> bytes:
        """Serve questions and events until the line starting with `answer`; its rest.

        Events come whenever the pins change, also before the first `run` (the pin levels at
        power-on), so every command's answer is read through here.
        """
        readline = self._process.stdout.readline
        while True:
            line = readline()
            kind, _, rest = line.rstrip(b'\n').partition(b' ')
            if kind == answer:
                return rest
            if kind == b'tx':
                self.output += bytes.fromhex(rest.decode('ascii'))
            elif kind == b'adc':
                self._send(f'{self._on_adc(int(rest))}\n')
            elif kind == b'trig':
                self._send(f'{self._on_trigger(int(rest))}\n')
            elif kind == b'valves':
                cycle, inlet, exhaust = (int(field) for field in rest.split())
                self._on_valves(cycle, inlet, exhaust)
            elif kind == b'error':
                raise FirmwareStoppedError(rest.decode('ascii', 'replace').strip())
            elif not line:
                raise self._stopped()
            else:
                raise FirmwareStoppedError(f'pma_simavr said {line!r}')

    def run_to(self, cycle: int) -> None:
        if cycle > self.cycle:
            self._send(f'run {cycle}\n')
            self._until_done()

    def send_rx(self, data: bytes) -> None:
        """Bytes from the host, put on the RX line one frame time after another."""
        if data:
            self._send(f'rx {data.hex()}\n')

    def reset(self) -> None:
        self._send('reset\n')
        self.output.clear()
        self.cycle = 0
        self._until_done()

    def stats(self) -> FirmwareStats:
        """Counters since the last reset; the `window_` ones restart with each call."""
        self._send('stats\n')
        answer = self._serve_until(b'stats').decode('ascii')
        return FirmwareStats({key: int(value) for key, value in
                              (item.split('=') for item in answer.split())})

    def close(self) -> None:
        if self._process.poll() is None:
            try:
                self._process.stdin.close()
            except BrokenPipeError:
                pass
            try:
                self._process.wait(5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process.stdout.close()


def valve_from_pins(inlet: int, exhaust: int) -> Valve | None:
    """The pneumatics' valve state for these pin levels; None for both open at once."""
    inlet_open = inlet == INLET_OPEN_LEVEL
    exhaust_open = exhaust == EXHAUST_OPEN_LEVEL
    if inlet_open and exhaust_open:
        return None
    return Valve.FILL if inlet_open else Valve.VENT if exhaust_open else Valve.HOLD


class SimavrDevice:
    """SimDevice's interface (what fake_arduino.run drives) over the firmware on simavr.

    The rig steps at 1 ms in device time, with the valve state the pins had at the start of
    each step. Both valves open at once (the firmware never does it) is counted, logged, and
    vents the muscle.
    """

    def __init__(self, config: DeviceConfig, rig: Rig, simulator_path: Path,
                 firmware_path: Path):
        self.config = config
        self.rig = rig
        self._sensor = PressureCalibration()
        self.simulator = FirmwareSimulator(simulator_path, firmware_path, self._adc_mv,
                                           self._echo_us, self._valves)
        self.both_valves_open = 0
        # Simulated and wall time spent simulating: their ratio is how much faster than the
        # board simavr runs here (below 1 it cannot keep up with the wall clock).
        self.simulated_ms = 0
        self.simulating_s = 0.0
        self._valve = Valve.HOLD
        self._physics_ms = 0
        self.t_ms = 0
        self._outbox: list[bytes] = []

    # -- the rig, in the AVR's time -----------------------------------------------------------
    def _physics_to(self, cycle: int) -> None:
        for _ in range(cycle // CYCLES_PER_MS - self._physics_ms):
            self.rig.step(1e-3, self._valve)
        self._physics_ms = max(self._physics_ms, cycle // CYCLES_PER_MS)

    def _adc_mv(self, cycle: int) -> int:
        """The millivolts on A0 that the ADC converts to the rig's count (simavr floors)."""
        self._physics_to(cycle)
        count = self.rig.read_adc()
        reference_mv = round(self._sensor.adc_reference_v * 1000)
        return math.ceil(count * reference_mv / 1023)

    def _echo_us(self, cycle: int) -> int:
        self._physics_to(cycle)
        return self.rig.read_echo_us()

    def _valves(self, cycle: int, inlet: int, exhaust: int) -> None:
        self._physics_to(cycle)
        valve = valve_from_pins(inlet, exhaust)
        if valve is None:
            self.both_valves_open += 1
            log.error('the firmware opened both valves at once (%.3f s after boot)',
                      cycle / CPU_HZ)
            valve = Valve.VENT
        self._valve = valve

    # -- SimDevice's interface ----------------------------------------------------------------
    def boot(self) -> None:
        """Power-on reset of the AVR; the rig keeps its state."""
        self.simulator.reset()
        self.t_ms = 0
        self._physics_ms = 0
        self._outbox.clear()

    @property
    def next_sample_ms(self) -> int:
        """When to come back: the firmware keeps its own schedule, so every millisecond."""
        return self.t_ms + 1

    def advance_to(self, t_ms: int) -> None:
        if t_ms <= self.t_ms:
            return
        started = time.monotonic()
        self.simulator.run_to(t_ms * CYCLES_PER_MS)
        self.simulating_s += time.monotonic() - started
        self.simulated_ms += t_ms - self.t_ms
        self._physics_to(t_ms * CYCLES_PER_MS)
        self.t_ms = t_ms
        output = self.simulator.output
        end = output.rfind(b'\n') + 1
        if end:
            self._outbox += [line + b'\n' for line in bytes(output[:end]).split(b'\n')[:-1]]
            del output[:end]

    def receive(self, data: bytes) -> None:
        self.simulator.send_rx(data)

    def take_output(self) -> list[bytes]:
        out, self._outbox = self._outbox, []
        return out

    def close(self) -> None:
        self.simulator.close()


def add_options(parser: argparse.ArgumentParser) -> None:
    build = default_build_dir()
    parser.add_argument('--firmware', type=Path, default=build / 'pma_firmware.elf',
                        help=f'the AVR image to run (default {build}/pma_firmware.elf)')
    parser.add_argument('--simulator', type=Path, default=build / 'simavr' / 'pma_simavr',
                        help=f'the pma_simavr program (default {build}/simavr/pma_simavr)')


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    args = fake_arduino.parse_args(
        argv, prog=PROG, extend=add_options,
        description='The PMA firmware image on a simulated ATmega2560 (simavr), behind a '
                    'pseudo-terminal, in front of the simulated rig.')
    defaults = fake_arduino.parse_args([])
    for name, why in COMPILED.items():
        if getattr(args, name) != getattr(defaults, name):
            print(f"{PROG}: --{name.replace('_', '-')} is not for the real firmware: {why}",
                  file=sys.stderr)
            raise SystemExit(2)
    return args


def run(args: argparse.Namespace, stop: StopRequest) -> int:
    devices: list[SimavrDevice] = []

    def make_device(config: DeviceConfig, rig: Rig) -> SimavrDevice:
        devices.append(SimavrDevice(config, rig, args.simulator, args.firmware))
        return devices[-1]

    try:
        return fake_arduino.run(args, stop, make_device=make_device, prog=PROG)
    finally:
        for device in devices:
            try:
                print(device.simulator.stats().text(), flush=True)
            except FirmwareStoppedError as error:
                print(f'{PROG}: no firmware stats: {error}', flush=True)
            speed = device.simulated_ms / 1000 / max(device.simulating_s, 1e-9)
            print(f'{PROG}: simulation speed_vs_real_time={speed:.1f} '
                  f'both_valves_open={device.both_valves_open}', flush=True)
            device.close()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(stream=sys.stderr, level=args.log_level,
                        format=f'{PROG} %(levelname)s: %(message)s')
    try:
        fake_arduino.configs_from_args(args)
    except ValueError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return 2
    try:
        return run(args, stop_request())
    except FileNotFoundError as error:
        print(f'{PROG}: {error}', file=sys.stderr)
        return 2
    except FirmwareStoppedError as error:
        log.error('the firmware stopped: %s', error)
        return 1


if __name__ == '__main__':
    sys.exit(main())

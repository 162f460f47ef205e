"""The firmware's figures in docs/hardware.md ("Firmware in the loop"), measured on simavr.

    . tools/env.sh && python pma_driver/test/measure_firmware_simavr.py    # about a minute

Builds this checkout's image (and, for the rates beyond MAX_RATE_HZ, a copy with that limit
raised) and runs it in simulated time, so the figures are the image's, not this machine's.
test_firmware_simavr.py asserts the ones that are requirements; this also charts the limits.
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

from firmware_build import mutated_firmware, require_simulator, run_firmware_script
from test_firmware_build import COMMAND_CASES, command, protocol
from test_firmware_simavr import Bench, gaps_ms, startup_burst

RAISED_MAX_RATE_HZ = 250


def memory(build) -> None:
    flash = re.search(r'flash: .*', build.output).group(0)
    ram = re.search(r'RAM: .*', build.output).group(0)
    print(f'avr-size: {flash}; {ram}')
    worst = 0
    for line, _ in COMMAND_CASES:
        bench = Bench.start(build)
        bench.run(20)
        bench.device.receive(line.encode('latin-1') + b'\n')
        bench.run(80)
        worst = max(worst, bench.stats().stack_peak_bytes)
        bench.close()
    print(f'stack peak over every command line of the protocol tests: {worst} B')


def rate(build, rate_hz: int, echo_lost: float, seconds: int = 10) -> None:
    bench = Bench.start(build, echo_timeout_rate=echo_lost)
    bench.run(200)
    bench.send(*startup_burst(rate_hz))
    bench.run(1_000, heartbeat_ms=500)
    bench.stats()
    start = bench.t_ms
    for second in range(seconds):
        bench.send(command('SET', 100_000 + 20_000 * (second % 5)))
        bench.run(1_000, heartbeat_ms=500)
    stats = bench.stats()
    values = stats.values
    samples = bench.samples(since_ms=start + 100)
    seqs = [s.seq for s in samples]
    whole = seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    naks = sum(isinstance(r, protocol.Nak) for r in bench.replies())
    gaps = gaps_ms(samples)
    print(f'{rate_hz:3d} Hz, {100 * echo_lost:3.0f} % echoes lost: '
          f'{len(samples) / (seconds - 0.1):5.1f} samples/s, gaps {min(gaps)}-{max(gaps)} ms, '
          f'seq {"whole" if whole else "GAPS"}, NAKs {naks}, longest loop pass '
          f'{stats.window_longest_loop_us:5.0f} us, stack peak {stats.stack_peak_bytes} B, '
          f'free RAM {stats.free_ram_bytes} B, UART TX busy '
          f'{100 * values["tx_bytes"] * values["cycles_per_byte"] / values["cycle"]:2.0f} %, '
          f'RX backlog max {values["rx_backlog_max"]} B, RX overruns {values["rx_overruns"]}')
    bench.close()


def bursts(build) -> None:
    for count in (8, 16, 24, 28, 32):
        bench = Bench.start(build)
        bench.run(200)
        lines = [command('SET', 100_000 + k) for k in range(count)]
        bench.send(*lines)
        bench.run(2_000, heartbeat_ms=500)
        acks = sum(isinstance(r, protocol.Ack) and r.command == 'SET' for r in bench.replies())
        naks = sum(isinstance(r, protocol.Nak) for r in bench.replies())
        print(f'{count:2d} SET lines back to back ({sum(len(line) + 1 for line in lines)} B): '
              f'{acks} ACK, {naks} NAK, {count - acks - naks} unanswered')
        bench.close()


def main() -> int:
    with tempfile.TemporaryDirectory() as directory:
        scratch = Path(directory)
        build = require_simulator(run_firmware_script(scratch / 'build'))
        memory(build)
        for rate_hz in (20, 50):
            for echo_lost in (0.0, 1.0):
                rate(build, rate_hz, echo_lost)
        bursts(build)
        source = mutated_firmware(scratch, {})
        header = source / 'pma_firmware' / 'pma_protocol.h'
        header.write_text(header.read_text().replace(
            'const uint8_t MAX_RATE_HZ = 50;',
            f'const uint8_t MAX_RATE_HZ = {RAISED_MAX_RATE_HZ};'))
        raised = require_simulator(run_firmware_script(scratch / 'raised', source))
        print(f'with MAX_RATE_HZ raised to {RAISED_MAX_RATE_HZ} (a copy, not the shipped image):')
        for rate_hz in (100, 150, 200, 250):
            for echo_lost in (0.0, 1.0):
                rate(raised, rate_hz, echo_lost, seconds=5)
    return 0


if __name__ == '__main__':
    sys.exit(main())

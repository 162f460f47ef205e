"""Close a loop around the simulated device, in simulated time, knowing the true length.

A controller sees what the driver would publish (gauge pressure from the ADC count, length
from the echo: same calibration, same noise, quantisation and echo timeouts) and answers
with a pressure setpoint, which reaches the device as the protocol's SET line. The true
length of the simulated muscle is recorded beside it for evaluation only: the controller
never sees it. Used by pma_control's tests and benchmarks, and by nothing at run time.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pma_common import protocol
from pma_common.calibration import LengthCalibration, PressureCalibration
from pma_common.protocol import Command
from pma_sim.device import DeviceConfig, Rig, SimDevice

# (time [s], gauge pressure [Pa], measured length [m] or NaN) -> pressure setpoint [Pa]
Controller = Callable[[float, float, float], float]


@dataclass
class Trace:
    """Per sample: what the controller saw and did, and the truth beside it."""

    t_s: list[float] = field(default_factory=list)
    pressure_pa: list[float] = field(default_factory=list)
    measured_length_m: list[float] = field(default_factory=list)
    true_length_m: list[float] = field(default_factory=list)
    command_pa: list[float] = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(values) for name, values in vars(self).items()}


def run_closed_loop(controller: Controller, duration_s: float, *, rate_hz: int = 20,
                    seed: int = 0, rig: Rig | None = None,
                    config: DeviceConfig | None = None, command_delay_s: float = 0.0) -> Trace:
    """Run `controller` on every sample of a simulated device for `duration_s`.

    `command_delay_s`: how long a setpoint takes from the controller to the device (on the
    real rig: DDS to the driver, the serial line, the firmware's next loop; 10-150 ms
    depending on the machine's load); bench_control measures what it costs the tracking.
    """
    delay_ms = round(command_delay_s * 1000)
    if delay_ms < 0:
        raise ValueError(f'command_delay_s must be >= 0, got {command_delay_s!r}')
    in_flight: deque[tuple[int, bytes]] = deque()        # (device time due, SET line)
    config = config or DeviceConfig(rate_hz=rate_hz, max_rate_hz=max(rate_hz, 20),
                                    heartbeat_check=False, seed=seed)
    device = SimDevice(config, rig=rig or Rig(config))
    pressure_cal, length_cal = PressureCalibration(), LengthCalibration()
    decoder = protocol.FrameDecoder()
    trace = Trace()
    sent_pa: int | None = None
    end_ms = int(duration_s * 1000)
    while device.t_ms < end_ms:
        while in_flight and in_flight[0][0] <= device.next_sample_ms:
            due_ms, line = in_flight.popleft()
            device.advance_to(due_ms)
            device.receive(line)
        device.advance_to(device.next_sample_ms)
        for frame in decoder.feed(b''.join(device.take_output())):
            if not isinstance(frame, protocol.Sample):
                continue
            t_s = frame.t_ms / 1000.0
            pressure = pressure_cal.adc_to_pa(frame.adc)
            measured = length_cal.echo_to_length_m(frame.echo_us)      # NaN: no echo
            command = float(controller(t_s, pressure, measured))
            setpoint = max(0, min(round(command), device.ceiling_pa))
            if setpoint != sent_pa:
                # Delivered before the device runs on (at once when there is no delay).
                in_flight.append((device.t_ms + delay_ms,
                                  protocol.encode_command(Command.SET, setpoint)))
                sent_pa = setpoint
            trace.t_s.append(t_s)
            trace.pressure_pa.append(pressure)
            trace.measured_length_m.append(measured)
            trace.true_length_m.append(device.rig.length_m)
            trace.command_pa.append(command)
    return trace

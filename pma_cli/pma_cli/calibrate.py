"""`pma calibrate`: the guided calibration of both sensors on the running rig.

1. pressure zero: vent, wait until the pressure is steady, tare (the driver's ~/tare);
2. pressure span: hold a check pressure, average the raw ADC, ask for the reference gauge's
   reading and correct calibration.volts_at_full;
3. length offset: at rest, average the echo, ask for the tape-measured length and set
   calibration.length_offset_m.
Then it shows old and new values, applies them to the driver in one atomic parameter set (the
driver checks them again), writes a params file the driver loads with --params-file, and with
--bag records what it measured with the result in the bag's custom_data. Every sweep bag the
driver records from then on carries the new calibration.* values in its metadata too.
Out-of-bounds results are refused and nothing is changed; Ctrl-C vents and changes nothing.
"""

from __future__ import annotations

import math
import select
import sys
from pathlib import Path

from rcl_interfaces.srv import SetParametersAtomically
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from pma_bag import BagWriteError, BagWriter
from pma_cli import calibration_arithmetic as cal
from pma_cli import quantities as q
from pma_cli.commands import DRIVER, Parameters, Setpoints
from pma_cli.session import FAILED, INTERRUPTED, OK, USAGE, CliError, Interrupted, Session
from pma_common import names
from pma_common.driver_parameters import PARAMETERS

MEASURE_S = 2.0
REST_WAIT_S = 2.0          # after the pressure is steady: the length creeps a little longer
GEOMETRY = """\
Length sensor geometry (docs/hardware.md, "Length sensor geometry"): the HC-SR04 sits on the
muscle's axis beyond its free end and looks at the plate on that end. The driver publishes
    length_m = length_offset_m + range_sign * range_m
With range_sign -1 (the sensor faces the muscle), length_offset_m is the distance from the
muscle's fixed end (its clamp) to the sensor's face. Measure the muscle at rest from its fixed
clamp to the plate on its free end: that is the length you type."""


class Prompter:
    """Questions on stdin that a stop signal interrupts (input() would not return for Ctrl-C)."""

    def __init__(self, session: Session, assume_yes: bool):
        self.session = session
        self.assume_yes = assume_yes

    def ask(self, question: str) -> str:
        print(question, end='', flush=True)
        while True:
            # Keep the subscriptions fed while the person reads a gauge.
            self.session.spin_until(lambda: False, 0.05)
            readable, _, _ = select.select([sys.stdin], [], [], 0.05)
            if readable:
                line = sys.stdin.readline()
                if not line:
                    raise CliError('no answer: standard input closed')
                if not sys.stdin.isatty():
                    print(line.rstrip('\n'))            # a transcript shows the answer
                return line.strip()

    def confirm(self, question: str) -> bool:
        if self.assume_yes:
            print(f'{question} [Y/n] y (--yes)')
            return True
        answer = self.ask(f'{question} [Y/n] ').lower()
        return answer in ('', 'y', 'yes')

    def quantity(self, question: str, kind: str):
        while True:
            text = self.ask(question)
            try:
                return q.parse(text, kind)
            except q.QuantityError as error:
                print(f'  {error}')


def _collect(session: Session, setpoints: Setpoints, duration_s: float) -> list:
    states = []
    setpoints.state.on_message(states.append)
    try:
        session.spin_for(duration_s)
    finally:
        setpoints.state._callbacks.remove(states.append)
    return states


class Calibration:
    def __init__(self, session: Session, prompter: Prompter, timeout_s: float):
        self.session = session
        self.prompt = prompter
        self.timeout_s = timeout_s
        self.setpoints = Setpoints(session)
        self.params = Parameters(session, DRIVER, timeout_s)
        self.recorded: list = []              # every state seen, for --bag
        self.setpoints.state.on_message(self.recorded.append)
        self.notes: list[str] = []
        self.changes: dict[str, float] = {}
        self.rest_adc: cal.Measurement | None = None      # the zero the span is measured from

    def driver_values(self) -> dict:
        return self.params.values(list(PARAMETERS))

    def vent_and_wait(self) -> None:
        self.setpoints.command(0.0, self.timeout_s)
        state = self.setpoints.steady(timeout_s=30.0)
        print(f'  vented and steady at {q.kpa(state.gauge_pressure_pa)}')

    def zero(self) -> None:
        print('\n1/3 pressure zero: venting, then tare at rest')
        self.vent_and_wait()
        states = _collect(self.session, self.setpoints, MEASURE_S)
        self.rest_adc = cal.Measurement.of([s.pressure_adc for s in states])
        print(f'  at rest: ADC {self.rest_adc.mean:.2f} counts (sd {self.rest_adc.stdev:.2f}) '
              f'over {self.rest_adc.count} samples')
        client = self.session.node.create_client(Trigger, f'{DRIVER}/tare')
        answer = self.session.call(client, Trigger.Request(), self.timeout_s, 'is the driver up?')
        if not answer.success:
            raise CliError(f'tare refused: {answer.message}')
        print(f'  {answer.message}')
        self.notes.append(f'tare: {answer.message}')

    def span(self, values: dict, check_pa: float) -> None:
        print(f'\n2/3 pressure span: the muscle is inflated to {q.kpa(check_pa, 0)} and held; '
              'read the reference gauge on it')
        if not self.prompt.confirm(f'Inflate to {q.kpa(check_pa, 0)} now?'):
            print('  span check skipped')
            return
        self.setpoints.command(check_pa, self.timeout_s)
        # The device regulates on its own reading; the driver converts with the span under
        # test, so a span error shows here as an offset from the setpoint. Any offset the
        # check would not refuse is waited through, then the pressure must stop moving.
        tolerance_pa = max(values['sweep.tolerance_pa'], cal.MAX_SPAN_ERROR * check_pa)
        self.setpoints.settle(check_pa, tolerance_pa, 30.0)
        self.setpoints.steady(timeout_s=30.0)
        states = _collect(self.session, self.setpoints, MEASURE_S)
        adc = cal.Measurement.of([s.pressure_adc for s in states])
        reading = cal.Measurement.of([s.gauge_pressure_pa for s in states])
        print(f'  held: the sensor reads {q.kpa(reading.mean)} (+/- {q.kpa(reading.stdev)}; '
              f'ADC {adc.mean:.1f} counts over {adc.count} samples)')
        reference = self.prompt.quantity(
            '  Reference gauge reading (e.g. 301kPa, 3.01bar, 43.6psi; plain = Pa): ', 'pressure')
        self.setpoints.command(0.0, self.timeout_s)
        result = cal.span_from_reference(values, adc, reference, self.rest_adc.mean)
        print(f'  span factor {result.factor:.4f} (sensor {q.kpa(result.reading_pa)}, gauge '
              f'{q.kpa(result.reference_pa)}): volts_at_full '
              f'{values["calibration.volts_at_full"]:.4f} -> {result.volts_at_full:.4f} V')
        self.changes['calibration.volts_at_full'] = result.volts_at_full
        self.changes['calibration.tare_offset_pa'] = result.tare_offset_pa
        self.notes.append(f'span: ADC {adc.mean:.2f} (sd {adc.stdev:.2f}, n {adc.count}) over '
                          f'{self.rest_adc.mean:.2f} at rest read {result.reading_pa:.0f} Pa, '
                          f'reference gauge {result.reference_pa:.0f} Pa, factor '
                          f'{result.factor:.5f}')

    def length(self, values: dict) -> None:
        print('\n3/3 length offset: the muscle at rest, measured with a tape')
        print('\n'.join(f'  {line}' for line in GEOMETRY.splitlines()))
        self.vent_and_wait()
        self.session.spin_for(REST_WAIT_S)
        states = _collect(self.session, self.setpoints, MEASURE_S)
        now = [s.length_m for s in states if math.isfinite(s.length_m)]
        if now:
            print(f'  the driver reads {q.cm(sum(now) / len(now))} now')
        tape = self.prompt.quantity('  Muscle length at rest by tape (e.g. 30.0cm, 300mm): ',
                                    'length')
        result = cal.length_offset_from_tape(values, [s.echo_us for s in states], tape)
        print(f'  range {q.cm(result.range_m)} at rest: length_offset_m '
              f'{values["calibration.length_offset_m"]:.4f} -> {result.length_offset_m:.4f} m '
              f'(reads {q.cm(result.previous_length_m)} now, {q.cm(tape)} after)')
        change = abs(result.length_offset_m - values['calibration.length_offset_m'])
        if change > cal.LARGE_OFFSET_CHANGE_M and not self.prompt.confirm(
                f'  That moves every length by {q.cm(change)}: was the tape on the muscle, '
                'clamp to plate? Keep it?'):
            print('  length offset not changed')
            return
        self.changes['calibration.length_offset_m'] = result.length_offset_m
        self.notes.append(f'length: range {result.range_m:.5f} m at rest, tape {tape:.4f} m')

    def apply(self, values: dict) -> dict:
        merged = cal.check_result(values, self.changes)
        client = self.session.node.create_client(
            SetParametersAtomically, f'{self.params.node}/set_parameters_atomically')
        request = SetParametersAtomically.Request(parameters=[
            Parameter(name, value=float(value)).to_parameter_msg()
            for name, value in self.changes.items()])
        result = self.session.call(client, request, self.timeout_s, 'is the driver up?').result
        if not result.successful:
            raise CliError(f'the driver refused the calibration: {result.reason}')
        return merged


def write_bag(path: Path, topic: str, states: list, custom_data: dict) -> None:
    writer = BagWriter(path, custom_data=custom_data)
    writer.add_topic(topic, 'pma_interfaces/msg/PmaState')
    for state in states:
        stamp = state.header.stamp
        writer.write(topic, serialize_message(state), stamp.sec * 1_000_000_000 + stamp.nanosec)
    writer.close()


def calibrate(session: Session, *, params_out: Path, check_pa: float | None, skip_pressure: bool,
              skip_length: bool, bag: Path | None, assume_yes: bool, timeout_s: float) -> int:
    prompter = Prompter(session, assume_yes)
    run = Calibration(session, prompter, timeout_s)
    run.setpoints.wait_for_driver(timeout_s)
    values = run.driver_values()
    before = dict(values)
    given = check_pa is not None
    check_pa = check_pa if given else 0.6 * values['max_gauge_pressure_pa']
    if not skip_pressure:
        try:
            cal.check_span_pressure(values, check_pa)     # before the tare changes anything
        except cal.CalibrationError as error:
            raise CliError(f'refused: {error}' + ('' if given else ' (the default, 60 % of '
                           'max_gauge_pressure_pa: give --check-pressure)'),
                           USAGE if given else FAILED) from None
    print(f'Calibrating {session.node_name(DRIVER)}: '
          + ', '.join(s for s, skip in (('pressure zero and span', skip_pressure),
                                        ('length offset', skip_length)) if not skip)
          + f'. The muscle will be vented{"" if skip_pressure else " and inflated"}: keep clear.')
    if not prompter.confirm('Start?'):
        return FAILED
    try:
        if not skip_pressure:
            run.zero()
            values = run.driver_values()           # the tare the driver just set
            run.span(values, check_pa)
        if not skip_length:
            run.length(values)
        run.setpoints.command(0.0, timeout_s)
        if not run.changes:
            print('\nnothing to change')
            return OK
        print('\nparameter                      before        after')
        for name, value in run.changes.items():
            print(f'{name:<30} {values[name]:<13.6g} {value:.6g}')
        merged = cal.check_result(values, run.changes)
        if not prompter.confirm(f'Apply to {run.params.node} and write {params_out}?'):
            print('nothing applied')
            return FAILED
        merged = run.apply(values)
        params_out.parent.mkdir(parents=True, exist_ok=True)
        params_out.write_text(cal.params_file_text(merged, run.notes), encoding='utf-8')
        print(f'applied; wrote {params_out.resolve()}')
        print(f'  load it at start: driver_node --ros-args --params-file {params_out.resolve()}'
              ' (after your rig file)')
        states = _collect(session, run.setpoints, 1.0)
        lengths = [s.length_m for s in states if math.isfinite(s.length_m)]
        if lengths:
            print(f'  the driver now reads {q.cm(sum(lengths) / len(lengths))} at rest')
        if bag is not None:
            data = {f'{name}': repr(float(merged[name])) for name in merged
                    if name.startswith('calibration.')}
            data.update({f'previous.{name}': repr(float(before[name])) for name in before
                         if name.startswith('calibration.')})
            data.update({f'calibration_note.{k}': note for k, note in enumerate(run.notes)})
            data['calibration_params_file'] = str(params_out.resolve())
            data['note'] = 'pma calibrate'
            try:
                write_bag(bag, session.resolve(names.STATE), run.recorded, data)
            except BagWriteError as error:
                raise CliError(f'applied and wrote {params_out}, but the bag failed: '
                               f'{error}') from None
            print(f'  bag of the calibration run: {bag.resolve()}')
        return OK
    except cal.CalibrationError as error:
        _vent_quietly(run)
        raise CliError(f'refused: {error}') from None
    except Interrupted:
        _vent_quietly(run)
        print('\ninterrupted: vented; no parameter changed (a tare already done stays)',
              file=sys.stderr)
        return INTERRUPTED
    except CliError:
        _vent_quietly(run)
        raise


def _vent_quietly(run: Calibration) -> None:
    """Setpoint 0 on the way out of a failed or interrupted run (no confirmation awaited)."""
    run.setpoints.publisher.publish(Float64(data=0.0))
    run.session.spin_until(lambda: False, 0.3, interruptible=False)

"""driver_node: the managed (lifecycle) ROS 2 driver of the PMA rig.

A thin node: parameters (parameters.py) configure a link.SerialLink (port, handshake,
heartbeats, reconnect); every sample is stamped (clock_sync) and published as
messages.sample_messages builds it; commands go through control.DeviceControl; the Sweep
action runs in sweep_runner.SweepRunner, recording through recorder_client.RecorderClient.
docs/driver.md documents parameters, topics, QoS, diagnostics and the lifecycle.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.exceptions import InvalidParameterValueException
from rclpy.lifecycle import Node, State, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure, Range
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from pma_common import names, protocol
from pma_common.driver_parameters import (
    PARAMETERS,
    calibrations,
    check_parameters,
    descriptor,
    stall_timeout_s,
    startup_commands,
)
from pma_common.node import WorkerPoolExecutor, ros_context, spin_until_stopped
from pma_common.parameters import node_or_exit
from pma_common.protocol import Command, Hello
from pma_common.service import SERVICE_QOS
from pma_driver.clock_sync import ClockSync
from pma_driver.command_gate import DeviceControl
from pma_driver.link import PortOpenError, SerialLink
from pma_driver.messages import FAULT_BITS, link_level, link_values, sample_messages
from pma_driver.recorder_client import RecorderClient
from pma_driver.sweep_runner import Outcome, SweepGoal, SweepRunner, SweepSettings
from pma_interfaces.action import Sweep
from pma_interfaces.msg import CommanderLease, PmaState, SweepRecord

# pma/sweep_record: a sweep's START, LEVELs and END; a reader that joins late (a recorder
# subscribed after the sweep began) still gets them.
SWEEP_RECORD_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
# pma/pressure_setpoint is taken best-effort: a setpoint the network held back is dropped, not
# delivered late. A reliable reader gets a writer's unacknowledged setpoints resent when a
# broken link returns, seconds after their commander was found lost and the muscle vented:
# that re-pressurised it (tests/test_lab_network.py). Any publisher matches; one-shot senders
# resend until the device shows the setpoint (`pma set`).
SETPOINT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)

# /diagnostics warns this long after a commander was lost (then 'last commander lost' says it).
LOST_WARN_S = 60.0


class PmaDriver(Node):
    """Lifecycle node: configure opens the port, activate publishes, cleanup closes it."""

    def __init__(self, **kwargs):
        super().__init__('driver_node', **kwargs)
        for name, (default, _, _) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor(name))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        values = self._values()
        # Overrides each passed their descriptor; together they must also make sense (a
        # ceiling the sensor cannot read, ...). Retrying configure cannot mend a parameter,
        # so such a start ends like a refused override (node_or_exit: exit code 2).
        reason = check_parameters(values, None)
        if reason:
            raise InvalidParameterValueException('parameters', '', reason)

        self._link: SerialLink | None = None
        self._control = DeviceControl(values['max_gauge_pressure_pa'], self._log,
                                      commander_timeout_s=values['commander_timeout_s'],
                                      commander_lost_action=values['commander_lost_action'])
        self._clock_sync = ClockSync()
        self._pressure_cal, self._length_cal = calibrations(values)
        self._frame_id = values['frame_id']
        self._ambient_pa = values['ambient_pressure_pa']
        self._published = 0
        self._unpublished = 0           # decoded while configured but not active
        self._last_fault = ('', '')     # (status text, ROS time) of the last fault bits
        self._last_commander_lost = ('', '', -math.inf)   # (what happened, ROS time, monotonic)
        self._rate_count = (0, time.monotonic())
        self._rate_hz = 0.0
        self._configure_error = ''
        self._pubs = None
        self._refusal_logged: dict[str, float] = {}

        self._record_pub = self.create_publisher(SweepRecord, names.SWEEP_RECORD,
                                                 SWEEP_RECORD_QOS)
        # A sweep's bag must hold its samples and its records: the recorder's readers of
        # both are heard before the first level.
        self._recorder = RecorderClient(self, values['sweep.recorder'],
                                        values['sweep.recorder_timeout_s'],
                                        publishers=lambda: (*(self._pubs or ()),
                                                            self._record_pub),
                                        last_words=lambda: (self._record_pub,))
        self._sweeps = SweepRunner(self._control, recorder=self._recorder,
                                   sample_count=lambda: self._published, on_event=self._log,
                                   now_ns=lambda: self.get_clock().now().nanoseconds)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS, 1)
        self.create_timer(1.0, self._publish_diagnostics)
        self.create_subscription(Float64, names.PRESSURE_SETPOINT, self._on_setpoint,
                                 SETPOINT_QOS)
        # Remote commanders' leases (docs/driver.md "Commander lease"): checked 10 times a
        # timeout, so a loss is acted on within 1.1 timeouts.
        self.create_subscription(CommanderLease, names.COMMANDER_LEASE, self._on_lease, 10)
        self._lease_timer = self.create_timer(values['commander_timeout_s'] / 10,
                                              self._check_leases)
        # Every goal is accepted: one that cannot run is aborted at once with the reason in
        # its result, which a client at a terminal sees (a rejection carries no reason).
        # Its goal, result and cancel services queue a burst as every service does.
        self._sweep_server = ActionServer(
            self, Sweep, names.SWEEP, execute_callback=self._execute_sweep,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup(), goal_service_qos_profile=SERVICE_QOS,
            result_service_qos_profile=SERVICE_QOS, cancel_service_qos_profile=SERVICE_QOS)
        # Blocks on the device's reply, so it must not hold up the default group.
        self.create_service(Trigger, '~/tare', self._on_tare, qos_profile=SERVICE_QOS,
                            callback_group=ReentrantCallbackGroup())
        self._autostart_timer = None
        if values['autostart']:
            self._autostart_timer = self.create_timer(values['reconnect_period_s'],
                                                      self._autostart)
            self._autostart()

    # -- parameters ----------------------------------------------------------------------

    def _values(self, changed: list[Parameter] = ()) -> dict:
        values = {name: self.get_parameter(name).value for name in PARAMETERS}
        values.update({p.name: p.value for p in changed})
        return values

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Check only; no side effects (they happen in _apply_parameters)."""
        hello = self._link.hello if self._link is not None else None
        reason = check_parameters(self._values(params), hello)
        return SetParametersResult(successful=not reason, reason=reason)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        names = {p.name for p in params}
        values = self._values()
        if any(name.startswith('calibration.') for name in names):
            self._pressure_cal, self._length_cal = calibrations(values)
        self._ambient_pa = values['ambient_pressure_pa']
        self._control.max_gauge_pressure_pa = values['max_gauge_pressure_pa']
        self._recorder.timeout_s = values['sweep.recorder_timeout_s']
        self._control.leases.timeout_s = values['commander_timeout_s']
        self._control.commander_lost_action = values['commander_lost_action']
        if 'commander_timeout_s' in names:
            self.destroy_timer(self._lease_timer)
            self._lease_timer = self.create_timer(values['commander_timeout_s'] / 10,
                                                  self._check_leases)
        link = self._link
        if link is None:
            return
        link.heartbeat_period_s = values['heartbeat_period_s']
        link.reconnect_period_s = values['reconnect_period_s']
        link.handshake_timeout_s = values['handshake_timeout_s']
        link.stall_timeout_s = stall_timeout_s(values['sample_rate_hz'])
        commands = {'sample_rate_hz': (Command.RATE, max(1, round(values['sample_rate_hz']))),
                    'max_gauge_pressure_pa': (Command.MAX, self._control.ceiling_pa()),
                    'heartbeat_timeout_ms': (Command.HEARTBEAT_TIMEOUT,
                                             values['heartbeat_timeout_ms'])}
        for name, (command, value) in commands.items():
            if name in names and link.connected:
                self._control.send(command, value)

    def _startup_commands(self, hello: Hello):
        commands, warnings = startup_commands(self._values(), hello)
        for warning in warnings:
            self.get_logger().warning(warning)
        return commands

    # -- lifecycle -----------------------------------------------------------------------

    def _state_label(self) -> str:
        return self._state_machine.current_state[1]

    def _autostart(self) -> None:
        """Configure and activate by ourselves (no manager); retry while the port is missing."""
        label = self._state_label()
        if label == 'unconfigured':
            self.trigger_configure()
            label = self._state_label()
            if label == 'unconfigured':
                period = self.get_parameter('reconnect_period_s').value
                self.get_logger().warning(
                    f'autostart: configure failed ({self._configure_error}); retrying every '
                    f'{period:g} s', throttle_duration_sec=30.0)
        if label == 'inactive':
            self.trigger_activate()
        if self._state_label() in ('active', 'finalized') and self._autostart_timer is not None:
            self._autostart_timer.cancel()
            self.destroy_timer(self._autostart_timer)
            self._autostart_timer = None

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        values = self._values()
        reason = check_parameters(values, None)
        if reason:
            self._configure_error = reason
            self.get_logger().error(f'configure: {reason}')
            return TransitionCallbackReturn.FAILURE
        self._pressure_cal, self._length_cal = calibrations(values)
        link = SerialLink(
            values['port'], values['baud'], on_sample=self._on_sample, on_hello=self._on_hello,
            on_event=self._log, startup_commands=self._startup_commands,
            receive_clock_ns=lambda: self.get_clock().now().nanoseconds,
            reconnect_period_s=values['reconnect_period_s'],
            handshake_timeout_s=values['handshake_timeout_s'],
            heartbeat_period_s=values['heartbeat_period_s'],
            stall_timeout_s=stall_timeout_s(values['sample_rate_hz']))
        try:
            link.open()
        except PortOpenError as error:
            self._configure_error = str(error)
            self.get_logger().error(f'configure: {error}', throttle_duration_sec=30.0)
            return TransitionCallbackReturn.FAILURE
        self._configure_error = ''
        qos = QoSProfile(depth=values['qos_depth'], reliability=(
            ReliabilityPolicy.RELIABLE if values['qos_reliability'] == 'reliable'
            else ReliabilityPolicy.BEST_EFFORT))
        self._pubs = (self.create_lifecycle_publisher(PmaState, names.STATE, qos),
                      self.create_lifecycle_publisher(FluidPressure, names.PRESSURE, qos),
                      self.create_lifecycle_publisher(Range, names.RANGE, qos))
        self._link = self._control.link = link
        link.start()
        self.get_logger().info(f'configured: {values["port"]} open at {values["baud"]} baud')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        result = super().on_activate(state)
        self._control.active = True
        self.get_logger().info('active: publishing pma/state, pma/pressure, pma/range')
        return result

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._control.deactivate()
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self.shutdown_hardware()
        for pub in self._pubs or ():
            self.destroy_publisher(pub)
        self._pubs = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self.shutdown_hardware()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.shutdown_hardware()
        return TransitionCallbackReturn.SUCCESS

    def shutdown_hardware(self) -> None:
        """Vent the muscle and close the port (cleanup, shutdown, Ctrl-C, errors)."""
        with self._control.lock:
            self._control.active = False
            link, self._link, self._control.link = self._link, None, None
        if link is not None:
            link.stop(vent=True)
            if self.context.ok():  # after Ctrl-C the context is gone and so is /rosout
                self.get_logger().info(f'closed {link.port} (vented)')

    # -- link callbacks (link thread) ------------------------------------------------------

    def _log(self, level: int, message: str) -> None:
        # One call site per severity: rclpy refuses to log from one line at two severities.
        logger = self.get_logger()
        if level >= logging.ERROR:
            logger.error(message)
        elif level >= logging.WARNING:
            logger.warning(message)
        elif level >= logging.INFO:
            logger.info(message)
        else:
            logger.debug(message)

    def _on_hello(self, hello: Hello) -> None:
        # The device clock restarted: the old offset means nothing now.
        self._clock_sync.reset()
        if self._pressure_cal.tare_offset_pa != 0.0:
            # The device forgets its tare when it restarts; our offset stays. They differ
            # until the next ~/tare (at rest).
            self.get_logger().warning(
                'the device (re)started and has no tare, while calibration.tare_offset_pa is '
                f'{self._pressure_cal.tare_offset_pa:.1f} Pa: call ~/tare again at rest')

    def _on_sample(self, sample: protocol.Sample, receive_ns: int) -> None:
        stamp_ns = self._clock_sync.stamp(sample.t_ms, receive_ns)
        self._control.note_sample(sample, self._pressure_cal.adc_to_pa(sample.adc))
        if sample.status & FAULT_BITS:
            self._last_fault = (protocol.status_text(sample.status & FAULT_BITS),
                                f'{stamp_ns / 1e9:.3f}')
        pubs = self._pubs
        if not self._control.active or pubs is None:
            self._unpublished += 1
            return
        messages = sample_messages(
            sample, stamp_ns, frame_id=self._frame_id, pressure=self._pressure_cal,
            length=self._length_cal, ambient_pressure_pa=self._ambient_pa)
        try:
            for pub, msg in zip(pubs, messages, strict=True):
                pub.publish(msg)
        except Exception as error:  # shutting down under us: the link must survive it
            self.get_logger().warning(f'publish failed: {error}', throttle_duration_sec=5.0)
            return
        self._published += 1

    # -- setpoints and tare ----------------------------------------------------------------

    def _on_setpoint(self, msg: Float64) -> None:
        kind, reason = self._control.command_setpoint(msg.data)
        if kind == 'inactive':
            label = self._state_label()   # still 'active' while deactivating or shutting down
            reason = ('driver is leaving the active state' if label == 'active'
                      else f'driver is {label}, not active')
        # Throttled per kind, so a flood of one kind of refusal hides no other kind.
        now = time.monotonic()
        if reason and now - self._refusal_logged.get(kind, -math.inf) >= 1.0:
            self._refusal_logged[kind] = now
            self.get_logger().warning(f'refused setpoint: {reason}')

    def _on_lease(self, msg: CommanderLease) -> None:
        if not self._control.note_lease(msg.lease_id, msg.commander, msg.holding) and \
                msg.holding:
            self.get_logger().warning(
                f'{msg.commander} renews lease {msg.lease_id[:8]}, which ran out: its setpoints '
                'are refused until it lets go', throttle_duration_sec=2.0)

    def _check_leases(self) -> None:
        events = self._control.check_leases()
        if self._control.lease_check_held_up:
            # Judged at the next check instead: said, since a vent then comes that much later.
            self.get_logger().warning(
                'commander-lease check came over half a commander_timeout_s late (this '
                'process was held up); judging at the next one', throttle_duration_sec=5.0)
        for event in events:
            self._last_commander_lost = (event, f'{self.get_clock().now().nanoseconds / 1e9:.3f}',
                                         time.monotonic())
            self.get_logger().error(event)

    def _on_tare(self, _request, response):
        """Zero the pressure at rest, on the device and here, from the same ADC count.

        The device regulates on its own tared reading and the host converts the raw count
        with `calibration.tare_offset_pa`: TARE's ACK carries the count the device took as
        zero, and the host's offset is computed from exactly that count, so both agree.
        """
        response.success, response.message = self._tare()
        if response.success:
            self.get_logger().info(response.message)
        else:
            self.get_logger().warning(f'tare refused: {response.message}')
        return response

    def _tare(self) -> tuple[bool, str]:
        adc, reason = self._control.tare()
        if adc is None:
            return False, reason
        offset_pa = float(replace(self._pressure_cal, tare_offset_pa=0.0).adc_to_pa(adc))
        result = self.set_parameters([Parameter('calibration.tare_offset_pa', value=offset_pa)])[0]
        if not result.successful:
            return False, f'device tared, but calibration.tare_offset_pa refused: {result.reason}'
        return True, (f'tared: ADC {adc} is 0 Pa on the device and here '
                      f'(calibration.tare_offset_pa = {offset_pa:.1f} Pa)')

    # -- sweep action ----------------------------------------------------------------------

    def _execute_sweep(self, goal_handle):
        request = goal_handle.request
        values = self._values()
        feedback = Sweep.Feedback()

        def publish_feedback(progress) -> None:
            feedback.progress = progress.progress
            feedback.gauge_setpoint_pa = progress.gauge_setpoint_pa
            feedback.sample_count = progress.sample_count
            feedback.step_index = progress.step_index
            feedback.step_count = progress.step_count
            feedback.phase = progress.phase
            goal_handle.publish_feedback(feedback)

        sweep_id = bytes(goal_handle.goal_id.uuid).hex()

        def publish_record(record) -> None:
            self._record_pub.publish(sweep_record_message(record, sweep_id))

        goal = SweepGoal.of(request)
        report = self._sweeps.run(
            goal,
            SweepSettings(values['sweep.tolerance_pa'], values['sweep.step_timeout_s'],
                          rest_pa=values['sweep.rest_pa'],
                          rest_time_s=values['sweep.rest_time_s'],
                          rest_timeout_s=values['sweep.rest_timeout_s']),
            cancel_requested=lambda: goal_handle.is_cancel_requested,
            feedback=publish_feedback,
            calibration={k: v for k, v in values.items() if k.startswith('calibration.')},
            record=publish_record)
        {Outcome.SUCCEEDED: goal_handle.succeed, Outcome.ABORTED: goal_handle.abort,
         Outcome.CANCELED: goal_handle.canceled}[report.outcome]()
        return Sweep.Result(success=report.success, message=report.message,
                            bag_path=report.bag_path, sample_count=report.sample_count)

    # -- diagnostics -----------------------------------------------------------------------

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        count, since = self._rate_count
        self._rate_hz = (self._published - count) / max(1e-3, now - since)
        self._rate_count = (self._published, now)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [self.diagnostic_status()]
        self._diagnostics_pub.publish(array)

    def diagnostic_status(self) -> DiagnosticStatus:
        status = DiagnosticStatus()
        status.name = f'{self.get_fully_qualified_name()}: serial link'
        status.hardware_id = self.get_parameter('port').value
        values: dict[str, str] = {'lifecycle state': self._state_label()}
        link = self._link
        if link is None:
            status.level = DiagnosticStatus.ERROR if self._configure_error else DiagnosticStatus.OK
            status.message = self._configure_error or f'not configured ({self._state_label()})'
        else:
            stats = link.stats()
            pubs = self._pubs
            status.level, status.message = link_level(stats, self._control.latest)
            lost, _, lost_at = self._last_commander_lost
            if status.level == DiagnosticStatus.OK and time.monotonic() - lost_at < LOST_WARN_S:
                status.level, status.message = DiagnosticStatus.WARN, lost
            values.update(link_values(stats, link.baud))
            values.update({
                'sample rate [Hz]': f'{self._rate_hz:.1f}',
                'samples published': str(self._published),
                # matched readers, as this writer sees them: "is anyone listening?"
                'state subscribers': str(pubs[0].get_subscription_count() if pubs else 0),
                'samples while inactive': str(self._unpublished),
                'sweep running': 'yes' if self._control.sweep_running else 'no',
                # SETs sent for pma/pressure_setpoint, one in flight at a time, and the
                # setpoints replaced by a newer one while a SET awaited its answer
                'setpoints sent': str(self._control.setpoints_sent),
                'setpoints coalesced': str(self._control.setpoints_coalesced),
                'last fault': (f'{self._last_fault[0]} at {self._last_fault[1]} s'
                               if self._last_fault[0] else '-'),
                'commanders holding a lease': ', '.join(self._control.leases.holders()) or '-',
                'lease checks held up': str(self._control.leases.late_checks),
                'last commander lost': (f'{self._last_commander_lost[0]} at '
                                        f'{self._last_commander_lost[1]} s'
                                        if self._last_commander_lost[0] else '-'),
                'clock offset [s]': f'{self._clock_sync.offset_s:.6f}',
                'clock drift [ppm]': f'{self._clock_sync.drift_ppm:.0f}',
            })
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return status


def sweep_record_message(record, sweep_id: str) -> SweepRecord:
    """pma/sweep_record's message for one of the SweepRunner's records."""
    msg = SweepRecord(
        sweep_id=sweep_id, kind=int(record.kind), profile=record.profile,
        started_at_rest=record.started_at_rest,
        start_gauge_pressure_pa=float(record.start_gauge_pressure_pa),
        level_index=record.level_index, level_count=record.level_count,
        target_gauge_pressure_pa=float(record.target_gauge_pressure_pa),
        reached_gauge_pressure_pa=float(record.reached_gauge_pressure_pa),
        branch=int(record.branch), settled=record.settled, message=record.message)
    for stamp, ns in ((msg.header.stamp, record.stamp_ns), (msg.hold_start, record.hold_start_ns),
                      (msg.hold_end, record.hold_end_ns)):
        stamp.sec, stamp.nanosec = divmod(int(ns), 1_000_000_000)
    return msg


def main(args=None) -> int:
    with ros_context(args) as stop:
        node = node_or_exit(PmaDriver, 'driver_node')   # no guessing for the hardware
        executor = WorkerPoolExecutor(num_threads=4)
        try:
            spin_until_stopped(executor, node, stop)
        finally:
            node.shutdown_hardware()        # vent and close the port, whatever comes in
            executor.shutdown()
            node.destroy_node()
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""`pma status` and `pma watch`: what the rig does now, from /diagnostics and the topics."""

from __future__ import annotations

import collections
import math
import sys
import time
from dataclasses import dataclass

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from pma_cli import quantities as q
from pma_cli.session import (
    FAILED,
    INTERRUPTED,
    NO_ANSWER,
    OK,
    CliError,
    Interrupted,
    Session,
    ros_time_s,
)
from pma_common import names
from pma_common.sequence import SequenceTracker
from pma_interfaces.msg import ControlState, ModelParams, PmaPrediction, PmaState

LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
VALVES = {PmaState.VALVE_HOLD: 'hold', PmaState.VALVE_FILL: 'fill', PmaState.VALVE_VENT: 'vent'}
BRANCHES = {PmaPrediction.BRANCH_INCREASING: 'increasing',
            PmaPrediction.BRANCH_DECREASING: 'decreasing'}
MODES = {ControlState.MODE_IDLE: 'idle', ControlState.MODE_GOAL: 'goal',
         ControlState.MODE_STREAM: 'stream', ControlState.MODE_FAULT: 'fault',
         ControlState.MODE_HOLD: 'hold'}
STATUS_BITS = {PmaState.STATUS_OVERPRESSURE: 'OVERPRESSURE',
               PmaState.STATUS_HEARTBEAT_LOST: 'HEARTBEAT_LOST',
               PmaState.STATUS_ECHO_TIMEOUT: 'ECHO_TIMEOUT',
               PmaState.STATUS_SENSOR_RANGE: 'SENSOR_RANGE'}
DIAGNOSTICS_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS_PERIOD_S = 1.0      # every node of the project publishes at 1 Hz
# How long the node graph must stay unchanged before `pma status` believes it complete. A
# fresh process discovers the others one by one; a busy machine answers late (CI once saw
# model_node appear after the graph had been still for 1.2 s), so two diagnostics periods.
GRAPH_SETTLED_S = 2 * DIAGNOSTICS_PERIOD_S + 0.2
# A fresh process often learns of a running node only at that node's next periodic
# participant announcement (Fast DDS: every 3 s by default). Measured from a new process
# beside a running rig: nodes appeared 0.1-3.1 s after it started, and the graph could stand
# still for over 3 s before the last one came; so listen at least that period and one
# diagnostics period more, from the start.
PARTICIPANT_ANNOUNCEMENT_S = 3.0
MIN_LISTEN_S = PARTICIPANT_ANNOUNCEMENT_S + DIAGNOSTICS_PERIOD_S


def level_name(level) -> str:
    value = level[0] if isinstance(level, bytes | bytearray) else int(level)
    return LEVELS.get(value, str(value))


def status_text(bits: int) -> str:
    return '+'.join(name for bit, name in STATUS_BITS.items() if bits & bit) or 'ok'


@dataclass
class NodeStatus:
    """The newest diagnostic status of one node of our namespace."""

    node: str
    what: str
    level: str
    message: str
    values: dict[str, str]


def split_status_name(name: str) -> tuple[str, str, str]:
    """'/left/driver_node: serial link' -> ('/left', 'driver_node', 'serial link')."""
    fqn, _, what = name.partition(': ')
    namespace, _, node = fqn.rpartition('/')
    return namespace or '/', node, what


class Diagnostics:
    """The newest status per node of one namespace, from /diagnostics."""

    def __init__(self, session: Session):
        self.namespace = session.namespace
        self.by_node: dict[str, NodeStatus] = {}
        self.namespaces_seen: set[str] = set()
        session.node.create_subscription(DiagnosticArray, names.DIAGNOSTICS, self._on_array,
                                         DIAGNOSTICS_QOS)

    def _on_array(self, array: DiagnosticArray) -> None:
        for status in array.status:
            namespace, node, what = split_status_name(status.name)
            self.namespaces_seen.add(namespace)
            if namespace == self.namespace:
                self.by_node[node] = NodeStatus(
                    node, what, level_name(status.level), status.message,
                    {'hardware_id': status.hardware_id,
                     **{kv.key: kv.value for kv in status.values}})

    def get(self, node: str) -> NodeStatus | None:
        return self.by_node.get(node)


def _nodes_in(session: Session) -> list[str]:
    return sorted(name for name, namespace in session.node.get_node_names_and_namespaces()
                  if namespace == session.namespace and not name.startswith('_'))


def driver_line(status: NodeStatus | None) -> str:
    if status is None:
        return 'no diagnostics from driver_node'
    values = status.values
    parts = [status.message, values.get('lifecycle state', '?')]
    if 'sample rate [Hz]' in values:
        parts.append(f'{float(values["sample rate [Hz]"]):.1f} Hz')
    if values.get('firmware', '-') != '-':
        parts.append(values['firmware'])
    parts.append(f'port {values.get("hardware_id", "?")}')
    if values.get('lost samples', '0') != '0':
        parts.append(f'{values["lost samples"]} samples lost')
    if values.get('sweep running') == 'yes':
        parts.append('sweep running')
    return ' | '.join(parts)


def commander_line(status: NodeStatus | None) -> str | None:
    """Who holds a commander lease on the driver, and the last one it lost (None: neither)."""
    if status is None:
        return None
    holders = status.values.get('commanders holding a lease', '-')
    lost = status.values.get('last commander lost', '-')
    if holders == '-' and lost == '-':
        return None
    return f'commander {holders if holders != "-" else "none holds a lease"}' + (
        f' | last lost: {lost}' if lost != '-' else '')


def state_lines(state: PmaState | None) -> list[str]:
    if state is None:
        return ['pressure  - (no pma/state received)']
    return [f'pressure  {q.kpa(state.gauge_pressure_pa)} (setpoint '
            f'{q.kpa(state.gauge_setpoint_pa)}, valve {VALVES.get(state.valve_state, "?")}, '
            f'device {status_text(state.status)})',
            f'length    {q.cm(state.length_m)}' + ('' if math.isfinite(state.length_m)
                                                     else ' (no echo)')]


def model_line(status: NodeStatus | None, prediction: PmaPrediction | None,
               params: ModelParams | None) -> str | None:
    if status is None and prediction is None:
        return None
    parts = []
    if status is not None:
        parts.append(f'{status.level} {q.in_units(status.message)}')
    if params is not None:
        parts.append(f'{params.form} branches, {params.memory} memory')
    if prediction is not None:
        parts.append(f'predicts {q.cm(prediction.predicted_length_m)} on the '
                     f'{BRANCHES.get(prediction.branch, "?")} branch')
    if status is not None and status.values.get('params_file', '(none)') != '(none)':
        parts.append(f'params_file {status.values["params_file"]}')
    return 'model     ' + ' | '.join(parts)


def control_line(status: NodeStatus | None, control: ControlState | None) -> str | None:
    if status is None and control is None:
        return None
    parts = []
    if status is not None:
        # The controller's own words are SI (`holding 0.2750 m`): in cm and kPa, as the rest.
        parts.append(f'{status.level} {q.in_units(status.message)}')
    if control is not None:
        parts.append(f'mode {MODES.get(control.mode, control.mode)}')
        if control.mode in (ControlState.MODE_GOAL, ControlState.MODE_STREAM,
                            ControlState.MODE_HOLD):
            parts.append(f'target {q.cm(control.target_length_m)}, command '
                         f'{q.kpa(control.gauge_pressure_command_pa)}')
        elif control.message and q.in_units(control.message) not in parts[0]:
            # Why it let go (a fault, a release, a cancel).
            parts.append(q.in_units(control.message))
    return 'control   ' + ' | '.join(parts)


def status(session: Session, wait_s: float, listen_s: float) -> int:
    """Print the rig's state; OK when the driver streams without an error."""
    started = time.monotonic()
    diagnostics = Diagnostics(session)
    state = session.latest(PmaState, names.STATE)
    prediction = session.latest(PmaPrediction, names.PREDICTION)
    control = session.latest(ControlState, names.CONTROL_STATE)
    params = session.latest(ModelParams, names.MODEL_PARAMS, LATCHED_QOS)

    def streaming() -> bool:
        driver = diagnostics.get('driver_node')
        return driver is not None and driver.values.get('link state') == 'streaming' \
            and state.message is not None

    if wait_s > 0 and not session.spin_until(streaming, wait_s):
        driver = diagnostics.get('driver_node')
        why = (f'the driver says: {driver.message}' if driver is not None else
               session.where_hint(names.STATE, 'driver_node'))
        print(f'pma status: no streaming driver within {wait_s:g} s; {why}', file=sys.stderr)
        return NO_ANSWER

    listening_since = time.monotonic()
    graph = {'nodes': _nodes_in(session), 'since': listening_since}

    def heard_everyone() -> bool:
        # Diagnostics heard from every node seen, a graph unchanged for GRAPH_SETTLED_S, and
        # MIN_LISTEN_S since the start, for the nodes that announce themselves late.
        now, nodes = time.monotonic(), _nodes_in(session)
        if nodes != graph['nodes']:
            graph.update(nodes=nodes, since=now)
        if min(now - listening_since, now - graph['since']) < GRAPH_SETTLED_S \
                or now - started < MIN_LISTEN_S:
            return False
        if 'driver_node' not in nodes:
            return True      # settled without a driver: waiting longer would not bring one
        if diagnostics.get('driver_node') is None or state.message is None:
            return False
        return set(nodes) & {'model_node', 'length_controller'} <= set(diagnostics.by_node)

    session.spin_until(heard_everyone, listen_s)
    session.spin_for(0.1)                  # the prediction of the last state
    nodes = _nodes_in(session)
    driver = diagnostics.get('driver_node')
    print(f'namespace {session.namespace}   nodes: {", ".join(nodes) or "none"}')
    print(f'driver    {driver.level + " " if driver else ""}{driver_line(driver)}')
    line = commander_line(driver)
    if line:
        print(line)
    for line in state_lines(state.message):
        print(line)
    for line in (model_line(diagnostics.get('model_node'), prediction.message, params.message),
                 control_line(diagnostics.get('length_controller'), control.message)):
        if line:
            print(line)
    if driver is None:
        others = sorted(diagnostics.namespaces_seen - {session.namespace})
        hint = session.where_hint(names.STATE, 'driver_node')
        if others:
            hint += f' (diagnostics came from {", ".join(others)})'
        print(f'pma status: no driver in {session.namespace}: {hint}', file=sys.stderr)
        return NO_ANSWER
    errors = [s for s in diagnostics.by_node.values() if s.level == 'ERROR']
    for item in errors:
        print(f'pma status: {item.node}: {item.message}', file=sys.stderr)
    return FAILED if errors or driver.values.get('link state') != 'streaming' else OK


# -- watch ---------------------------------------------------------------------------------

WATCH_COLUMNS_HUMAN = ('t [s]', 'seq', 'p [kPa]', 'set [kPa]', 'L [cm]', 'model [cm]',
                       'branch', 'valve', 'status')
WATCH_COLUMNS_SI = ('time_s', 'seq', 'gauge_pressure_pa', 'gauge_setpoint_pa', 'length_m',
                    'predicted_length_m', 'branch', 'valve', 'status')
PREDICTION_WAIT_S = 0.3     # a state's line waits this long for its prediction


def _number(value: float, fmt: str) -> str:
    return format(value, fmt) if math.isfinite(value) else 'nan'


class RateLimit:
    """At most about `rate_hz` samples a second by their stamps, yet every sample of a stream
    at that rate.

    A token bucket: it refills at the rate, a shown sample takes a token, and it holds
    BURST tokens, so a sample stamped early borrows from one stamped late. (The stamps of a
    20 Hz stream are 50 ms apart give or take nanosecond rounding and the clock fit's
    corrections: comparing each with the last one shown dropped every one a nanosecond early,
    a third to a half of the stream at the default 20 Hz limit.) It refills TOLERANCE faster
    than the rate, for a device whose clock runs a little fast in host time.
    """

    BURST = 3.0
    TOLERANCE = 0.05

    def __init__(self, rate_hz: float):
        self.rate_hz = rate_hz * (1.0 + self.TOLERANCE) if rate_hz > 0 else math.inf
        self.tokens = self.BURST
        self.last_stamp: float | None = None

    def take(self, stamp_s: float) -> bool:
        """True if the sample stamped `stamp_s` is shown (its token taken)."""
        if math.isinf(self.rate_hz):
            return True
        if self.last_stamp is not None:
            elapsed = max(0.0, stamp_s - self.last_stamp)
            self.tokens = min(self.BURST, self.tokens + elapsed * self.rate_hz)
        self.last_stamp = stamp_s
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class Watch:
    """One line per sample (at most `max_rate_hz`), each with the model's prediction if any."""

    def __init__(self, session: Session, si: bool, max_rate_hz: float, out=sys.stdout):
        self.session = session
        self.si = si
        self.limit = RateLimit(max_rate_hz)
        self.out = out
        self.pending: collections.deque[tuple[float, PmaState]] = collections.deque()
        self.predictions: dict[tuple[int, int], PmaPrediction] = {}
        self.sequence = SequenceTracker()
        self.shown = 0
        self.received = 0
        self.last_received_at = math.nan
        self.t0: float | None = None
        qos = QoSProfile(depth=200, reliability=qos_profile_sensor_data.reliability)
        session.node.create_subscription(PmaState, names.STATE, self._on_state, qos)
        session.node.create_subscription(PmaPrediction, names.PREDICTION, self._on_prediction,
                                         qos)

    def _on_state(self, state: PmaState) -> None:
        self.received += 1
        self.last_received_at = time.monotonic()
        self.sequence.add(state.seq)
        self.pending.append((time.monotonic(), state))

    def _on_prediction(self, prediction: PmaPrediction) -> None:
        stamp = prediction.header.stamp
        self.predictions[(stamp.sec, stamp.nanosec)] = prediction
        if len(self.predictions) > 2000:
            for key in list(self.predictions)[:1000]:
                del self.predictions[key]

    def header(self) -> str:
        columns = WATCH_COLUMNS_SI if self.si else WATCH_COLUMNS_HUMAN
        widths = (9, 8, 10, 10, 9, 10, 10, 5, 0)
        return ' '.join(f'{c:>{w}}' if w else c for c, w in zip(columns, widths, strict=True))

    def line(self, state: PmaState, prediction: PmaPrediction | None) -> str:
        t = ros_time_s(state.header.stamp)
        if self.t0 is None:
            self.t0 = t
        predicted = prediction.predicted_length_m if prediction else math.nan
        branch = BRANCHES.get(prediction.branch, '-') if prediction else '-'
        if self.si:
            numbers = (f'{t - self.t0:9.3f}', f'{state.seq:8d}',
                       f'{_number(state.gauge_pressure_pa, ".1f"):>10}',
                       f'{_number(state.gauge_setpoint_pa, ".1f"):>10}',
                       f'{_number(state.length_m, ".5f"):>9}', f'{_number(predicted, ".5f"):>10}')
        else:
            # No prediction for the sample (no model_node, or the first samples, published
            # before this subscription was matched) reads '-', as the branch does; a
            # prediction of NaN reads 'nan'.
            model = _number(predicted * 100, '.2f') if prediction else '-'
            numbers = (f'{t - self.t0:9.3f}', f'{state.seq:8d}',
                       f'{_number(state.gauge_pressure_pa / 1e3, ".1f"):>10}',
                       f'{_number(state.gauge_setpoint_pa / 1e3, ".1f"):>10}',
                       f'{_number(state.length_m * 100, ".2f"):>9}', f'{model:>10}')
        return ' '.join((*numbers, f'{branch:>10}', f'{VALVES.get(state.valve_state, "?"):>5}',
                         status_text(state.status)))

    def flush(self, everything: bool = False, limit: int = 0) -> None:
        now = time.monotonic()
        while self.pending and not (limit and self.shown >= limit):
            received, state = self.pending[0]
            stamp = state.header.stamp
            prediction = self.predictions.pop((stamp.sec, stamp.nanosec), None)
            if prediction is None and not everything and now - received < PREDICTION_WAIT_S:
                return
            self.pending.popleft()
            if not self.limit.take(ros_time_s(stamp)):
                continue
            print(self.line(state, prediction), file=self.out, flush=True)
            self.shown += 1

    def run(self, count: int, first_timeout_s: float) -> int:
        print(self.header(), file=self.out, flush=True)
        hinted = False
        stalled = False             # said that the stream stopped (and not heard since)
        started = time.monotonic()
        code = OK
        try:
            while count <= 0 or self.shown < count:
                self.session.spin_until(lambda: False, 0.05)
                self.flush(limit=count)
                now = time.monotonic()
                if self.received == 0 and now - started > first_timeout_s:
                    hint = self.session.where_hint(names.STATE, 'driver_node')
                    if count > 0:
                        raise CliError(f'no pma/state within {first_timeout_s:g} s: {hint}',
                                       NO_ANSWER)
                    if not hinted:
                        print(f'pma watch: no pma/state yet: {hint}', file=sys.stderr)
                        hinted = True
                # A stream that stops (the driver ended, or was deactivated) ends a counted
                # watch: its last lines would never come (issue 50).
                silent_s = now - self.last_received_at
                if self.received and silent_s > first_timeout_s:
                    if count > 0:
                        self.flush(everything=True, limit=count)
                        raise CliError(f'pma/state stopped after {self.received} samples '
                                       f'(none for {first_timeout_s:g} s; {self.shown} of '
                                       f'{count} lines shown): is the driver still running '
                                       'and active?', NO_ANSWER)
                    if not stalled:
                        print(f'pma watch: no pma/state for {first_timeout_s:g} s (the driver '
                              'ended, or is inactive); still watching', file=sys.stderr)
                        stalled = True
                elif self.received and stalled and silent_s < 1.0:
                    stalled = False
        except Interrupted:
            self.flush(everything=True, limit=count)
            code = INTERRUPTED           # Ctrl-C, as every verb it stops (docs/cli.md)
        stats = self.sequence.stats()
        print(f'pma watch: {self.shown} lines, {self.received} samples received, '
              f'{stats.lost} lost by sequence number', file=sys.stderr)
        return code

"""`pma set`, `vent`, `tare`, `length` and `param`: one request each, answered in one line."""

from __future__ import annotations

import difflib
import math
import os
import re
import statistics
import sys
import time

import yaml
from action_msgs.srv import CancelGoal
from rcl_interfaces.msg import Log, ParameterType
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from pma_cli import quantities as q
from pma_cli.observe import BRANCHES, PARTICIPANT_ANNOUNCEMENT_S
from pma_cli.session import NO_ANSWER, OK, CliError, Latest, Session
from pma_common import names
from pma_common.driver_parameters import PARAMETERS, device_ceiling_pa
from pma_common.setpoint import setpoint_refusal
from pma_interfaces.msg import ControlState, PmaState
from pma_interfaces.srv import PressureForLength

DRIVER = 'driver_node'
SETPOINT_TOPIC = names.PRESSURE_SETPOINT
SETPOINT_RESEND_S = 0.5     # a setpoint not yet shown by the device is sent again this often
CONTROL_TOPIC = names.CONTROL_STATE
ROSOUT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
ABSENT_AFTER_S = 4.0        # a node not in the graph by then (which shows others) is not running
REST_PA = 25_000.0          # below this a vented muscle may be tared (the device's own bound)
SETTLE_WAIT_S = 30.0        # `pma set --wait`: inflating takes longer than a node's answer
CANCEL_ANSWER_S = 5.0       # `pma vent`: a goal server's answer to cancelling all its goals
CEILING = 'max_gauge_pressure_pa'   # the driver's ceiling, which `pma set` checks first
# What the driver checks against when started without the parameter (its declared default).
DEFAULT_CEILING_PA = device_ceiling_pa(PARAMETERS[CEILING][0], None)


# -- setpoints -----------------------------------------------------------------------------

class Setpoints:
    """Publish setpoints to the driver and see what became of them.

    A topic has no answer, so the device's own report is the confirmation (pma/state carries
    the setpoint the device regulates to) and the driver's log line on /rosout, `refused
    setpoint: ...`, is the refusal with its reason. A setpoint the driver would refuse by its
    value (negative, not finite, above `ceiling_pa`) is refused here instead, in the driver's
    words (pma_common.setpoint), and not published: every subscriber of the topic would see
    it. `ceiling_pa` is inf until read_ceiling (or the caller) sets it.
    """

    def __init__(self, session: Session):
        self.session = session
        self.ceiling_pa: float = math.inf
        self.ceiling_from = ''          # where ceiling_pa came from, said beside a refusal
        self.ceiling_read = False       # from the driver itself
        self.publisher = session.node.create_publisher(Float64, SETPOINT_TOPIC, 10)
        self.state = session.latest(PmaState, names.STATE, keep=200)
        self.control = session.latest(ControlState, CONTROL_TOPIC)
        self.refusals: list[tuple[float, str]] = []
        namespace = session.namespace.strip('/').replace('/', '.')
        self._driver_logger = f'{namespace}.{DRIVER}' if namespace else DRIVER
        session.node.create_subscription(Log, '/rosout', self._on_log, ROSOUT_QOS)

    def _on_log(self, log: Log) -> None:
        if log.name == self._driver_logger and log.msg.startswith('refused setpoint: '):
            self.refusals.append((time.monotonic(), log.msg.removeprefix('refused setpoint: ')))

    def wait_for_driver(self, timeout_s: float) -> None:
        """Until the driver's subscription is matched by our publisher (else NO_ANSWER)."""
        node = self.session.node
        topic = self.session.resolve(SETPOINT_TOPIC)

        def matched() -> bool:
            readers = node.get_subscriptions_info_by_topic(topic)
            driver = [r for r in readers if r.node_name == DRIVER
                      and r.node_namespace == self.session.namespace]
            return bool(driver) and self.publisher.get_subscription_count() >= len(readers) \
                and self.state.message is not None

        if not self.session.spin_until(matched, timeout_s, waiting_for=DRIVER):
            raise CliError(f'no driver takes setpoints on {topic} (waited {timeout_s:g} s): '
                           + self.session.where_hint(names.STATE, DRIVER)
                           + f' Start it: {self.session.start_hint(DRIVER)}', NO_ANSWER)

    def read_ceiling(self, timeout_s: float, absent_after_s: float | None = None) -> bool:
        """Set `ceiling_pa` from the driver (driver_ceiling_pa); False, and nothing changed,
        when it did not answer."""
        ceiling = driver_ceiling_pa(self.session, timeout_s, absent_after_s)
        if ceiling is None:
            return False
        self.ceiling_pa, self.ceiling_read = ceiling, True
        self.ceiling_from = f'the parameter of {self.session.node_name(DRIVER)}'
        return True

    def use_default_ceiling(self, waited_s: float, verb: str) -> None:
        """No driver answered: check against the parameter's default, and say so."""
        driver = self.session.node_name(DRIVER)
        self.ceiling_pa = DEFAULT_CEILING_PA
        self.ceiling_from = f"the parameter's default: {driver} did not answer"
        print(f'pma {verb}: note: no answer from {driver} for its {CEILING} within '
              f'{waited_s:.1f} s; checking against its default, {q.kpa(DEFAULT_CEILING_PA)}',
              file=sys.stderr, flush=True)

    def check(self, gauge_pa: float) -> None:
        check_setpoint(gauge_pa, self.ceiling_pa, self.ceiling_from)

    def command(self, gauge_pa: float, timeout_s: float) -> PmaState:
        """Send one setpoint; the first state that shows the device took it. CliError: why not."""
        self.check(gauge_pa)
        target = round(gauge_pa)
        sent_at = time.monotonic()
        seen = self.state.count
        self.publisher.publish(Float64(data=float(gauge_pa)))
        resent_at = sent_at

        def answered() -> bool:
            nonlocal resent_at
            if any(at >= sent_at for at, _ in self.refusals):
                return True
            state = self.state.message
            if self.state.count > seen and abs(state.gauge_setpoint_pa - target) < 0.5:
                return True
            # The driver takes setpoints best-effort (never late): one lost on the way is
            # sent again; the same setpoint twice is that setpoint once.
            if time.monotonic() - resent_at >= SETPOINT_RESEND_S:
                resent_at = time.monotonic()
                self.publisher.publish(Float64(data=float(gauge_pa)))
            return False

        if not self.session.spin_until(answered, timeout_s):
            why = ('the length controller follows a target and overwrote it' if
                   holds_target(self.control.message) else 'the driver log says why')
            raise CliError(f'the device did not report setpoint {q.kpa(gauge_pa)} within '
                           f'{timeout_s:g} s ({why})')
        refused = [reason for at, reason in self.refusals if at >= sent_at]
        if refused:
            raise CliError(f'the driver refused {q.kpa(gauge_pa)}: {refused[-1]}')
        return self.state.message

    def controller_warning(self) -> str:
        """A warning when the length controller would overwrite a setpoint of ours."""
        if holds_target(self.control.message):
            return ('warning: the length controller follows a target and commands its own '
                    'pressure; cancel its goal (`pma vent` does) or stop the length stream')
        return ''

    def settle(self, target_pa: float, tolerance_pa: float, timeout_s: float,
               show=None) -> PmaState:
        """Until the measured pressure stays within tolerance of the target for 0.5 s."""
        inside_since = [None]

        def settled() -> bool:
            state = self.state.message
            if show is not None:
                show(state)
            if abs(state.gauge_pressure_pa - target_pa) > tolerance_pa:
                inside_since[0] = None
                return False
            inside_since[0] = inside_since[0] or time.monotonic()
            return time.monotonic() - inside_since[0] >= 0.5

        if not self.session.spin_until(settled, timeout_s):
            raise CliError(f'pressure {q.kpa(self.state.message.gauge_pressure_pa)} did not '
                           f'settle within {q.kpa(tolerance_pa)} of {q.kpa(target_pa)} in '
                           f'{timeout_s:g} s')
        return self.state.message

    def steady(self, window_s: float = 1.0, timeout_s: float = 20.0) -> PmaState:
        """Until the pressure stops moving: two successive windows agree within noise.

        Only states from now on count (the history may hold a steady hold just left).
        """
        self.state.history.clear()

        def still() -> bool:
            history = self.state.history
            if len(history) < 8:
                return False
            newest = ros_stamp(history[-1])
            recent = [s.gauge_pressure_pa for s in history if newest - ros_stamp(s) < window_s]
            before = [s.gauge_pressure_pa for s in history
                      if window_s <= newest - ros_stamp(s) < 2 * window_s]
            if len(recent) < 4 or len(before) < 4:
                return False
            noise = max(statistics.pstdev(recent), statistics.pstdev(before), 500.0)
            return abs(statistics.fmean(recent) - statistics.fmean(before)) < 3 * noise \
                / math.sqrt(len(recent))
        if not self.session.spin_until(still, timeout_s):
            raise CliError(f'the pressure did not settle within {timeout_s:g} s (a leak, or '
                           'the supply still changing?)')
        return self.state.message


def driver_ceiling_pa(session: Session, timeout_s: float,
                      absent_after_s: float | None = None) -> int | None:
    """The driver's max_gauge_pressure_pa, whole Pa as the driver takes it; None when it did
    not answer within `timeout_s`.

    A query, resent while unanswered. With `absent_after_s`, gives up once that long after
    the session started the driver is not in the graph (discovery has had time to find it:
    ABSENT_AFTER_S). The device's own limit may be lower still: that the driver checks, and
    refuses (DeviceControl.ceiling_pa).
    """
    driver = session.node_name(DRIVER)
    client = session.node.create_client(GetParameters, f'{driver}/get_parameters')
    deadline = time.monotonic() + timeout_s

    def ready_or_absent() -> bool:
        if client.service_is_ready():
            return True
        if absent_after_s is None or time.monotonic() - session.started < absent_after_s:
            return False
        return driver not in {f'{ns.rstrip("/")}/{name}' for name, ns
                              in session.node.get_node_names_and_namespaces()}

    try:
        session.spin_until(ready_or_absent, timeout_s, waiting_for=DRIVER)
        if not client.service_is_ready():
            return None
        try:
            answer = session.answer(client, GetParameters.Request(names=[CEILING]),
                                    max(deadline - time.monotonic(), 1.0), query=True)
        except CliError:
            return None
        values = answer.values
        if len(values) != 1 or values[0].type != ParameterType.PARAMETER_DOUBLE:
            return None
        return device_ceiling_pa(values[0].double_value, None)
    finally:
        session.node.destroy_client(client)


def check_setpoint(gauge_pa: float, ceiling_pa: float, ceiling_from: str = '') -> None:
    """CliError (exit 1) for a setpoint the driver would refuse by its value, in the driver's
    own words (pma_common.setpoint); `ceiling_from` says where the ceiling came from."""
    kind, reason = setpoint_refusal(gauge_pa, ceiling_pa)
    if reason:
        source = f' ({ceiling_from})' if kind == 'too high' and ceiling_from else ''
        raise CliError(f'refused {q.kpa(gauge_pa)}: {reason}{source}; nothing was sent')


def ros_stamp(state: PmaState) -> float:
    return state.header.stamp.sec + 1e-9 * state.header.stamp.nanosec


def holds_target(control: ControlState | None) -> bool:
    """The length controller steers to a length: it commands a pressure on every sample."""
    return control is not None and control.mode in (
        ControlState.MODE_GOAL, ControlState.MODE_STREAM, ControlState.MODE_HOLD)


def set_pressure(session: Session, gauge_pa: float, wait: bool, tolerance_pa: float,
                 timeout_s: float) -> int:
    """Check the pressure against the driver's ceiling, release a holding controller,
    command, and with `wait` wait up to SETTLE_WAIT_S (or the timeout, if longer) for the
    pressure: `timeout_s` is how long a node may take to answer.

    Nothing is published that the driver would refuse by its value: a negative pressure at
    once; one above its max_gauge_pressure_pa once that is read, or, when no driver is found
    within ABSENT_AFTER_S, above the parameter's default, without waiting for one.
    """
    setpoints = Setpoints(session)
    setpoints.check(gauge_pa)                  # negative or not finite: no ceiling needed
    short_s = min(timeout_s, ABSENT_AFTER_S)
    if not setpoints.read_ceiling(timeout_s, absent_after_s=short_s):
        setpoints.use_default_ceiling(time.monotonic() - session.started, 'set')
    setpoints.check(gauge_pa)
    setpoints.wait_for_driver(timeout_s)
    if not setpoints.ceiling_read:
        setpoints.read_ceiling(timeout_s)      # a driver found late: its own ceiling
        setpoints.check(gauge_pa)
    release_holding_controller(session, setpoints.control, timeout_s)
    state = setpoints.command(gauge_pa, timeout_s)
    print(f'setpoint {q.kpa(gauge_pa)} taken by the device (pressure now '
          f'{q.kpa(state.gauge_pressure_pa)})')
    warning = setpoints.controller_warning()
    if warning:
        print(f'pma set: {warning}', file=sys.stderr)
    if wait:
        started = time.monotonic()
        state = setpoints.settle(gauge_pa, tolerance_pa, max(timeout_s, SETTLE_WAIT_S))
        print(f'reached {q.kpa(state.gauge_pressure_pa)} in {time.monotonic() - started:.1f} s')
    return OK


def cancel_all_goals(session: Session, action: str, timeout_s: float = 1.0) -> int | None:
    """Cancel every goal of an action (zero id and stamp: all, by the action protocol).

    Returns how many goals were cancelling; 0 when no server is there (none running); None
    when the server did not answer within CANCEL_ANSWER_S. Cancelling all twice is cancelling
    all once, so the request is resent while unanswered (an answer to a new client can be
    lost, pma_common.service).
    """
    client = session.node.create_client(CancelGoal, f'{action}/_action/cancel_goal')
    service = session.resolve(f'{action}/_action/cancel_goal')

    def in_graph() -> bool:
        return any(name == service for name, _ in session.node.get_service_names_and_types())

    try:
        # A server the graph shows but this client has not matched yet (a loaded machine
        # takes seconds) is one whose goals may run: it gets CANCEL_ANSWER_S to match.
        if not session.spin_until(lambda: client.service_is_ready() or in_graph(), timeout_s):
            return 0
        if not session.spin_until(client.service_is_ready, CANCEL_ANSWER_S):
            return None
        try:
            response = session.answer(client, CancelGoal.Request(), CANCEL_ANSWER_S,
                                      query=True)
        except CliError:
            return None
        return len(response.goals_canceling)
    finally:
        session.node.destroy_client(client)


def release_controller(session: Session, control: ControlState, timeout_s: float) -> bool:
    """Make a length controller that holds a target stop commanding.

    A MoveToLength goal that succeeded (or a stream that stopped) leaves the controller
    holding its target, and it has no "release"; cancelling a goal clears the target
    (docs/control.md). So: a goal for the target it holds anyway, cancelled at once. A stream
    still being sent sets a target again with its next message (then `pma vent` warns).
    """
    from rclpy.action import ActionClient

    from pma_interfaces.action import MoveToLength

    client = ActionClient(session.node, MoveToLength, names.MOVE_TO_LENGTH)
    try:
        if not session.spin_until(client.server_is_ready, timeout_s):
            return False
        goal = MoveToLength.Goal(length_m=control.target_length_m)
        handle = session.send_goal(client, goal, timeout_s, 'the length controller')
        result = handle.get_result_async()
        # The goal's end is its result, whose answers send_goal has seen reach us; the
        # cancel's own answer comes on another service and can be lost (pma_common.service).
        handle.cancel_goal_async()
        session.wait_future(result, timeout_s, 'the length controller')
        return True
    finally:
        client.destroy()


def release_holding_controller(session: Session, control: Latest, timeout_s: float) -> None:
    """Release a length controller that holds a target, and say so: it would overwrite a
    setpoint of ours at its next sample, or take the muscle back once a sweep ends.

    `control` is a pma/control_state subscription; the controller publishes it with every
    sample. A fresh process may learn of the controller only at its next participant
    announcement, a second or more after the driver (measured: up to 1.1 s later, 2.8 s from
    the start): one not seen by then is taken as not running. Not waiting costs more than
    the wait: the controller lets go by itself of a target when another node's setpoint
    reaches it, but a setpoint sent before the controller has matched this process's
    publisher never does, and the controller overwrites it.
    """
    topic = session.resolve(CONTROL_TOPIC)

    def known() -> bool:
        return control.message is not None or (
            not session.node.count_publishers(topic)
            and time.monotonic() - session.started >= PARTICIPANT_ANNOUNCEMENT_S)

    session.spin_until(known, timeout_s)
    held = control.message
    if holds_target(held) and math.isfinite(held.target_length_m) \
            and release_controller(session, held, timeout_s):
        print(f'released the length controller (it held {q.cm(held.target_length_m)})',
              flush=True)
        session.spin_for(0.3)          # its last setpoints reach the driver before ours


def vent(session: Session, wait: bool, timeout_s: float) -> int:
    """Cancel any sweep or move, release a holding controller, then command 0 Pa."""
    setpoints = Setpoints(session)
    setpoints.wait_for_driver(timeout_s)
    # What comes before the 0 Pa setpoint must not keep it from being sent: an unanswered
    # cancel or release is reported, and the muscle vented all the same.
    cancelled = {action: cancel_all_goals(session, action)
                 for action in (names.SWEEP, names.MOVE_TO_LENGTH)}
    for action, count in cancelled.items():
        if count is None:
            print(f'pma vent: warning: {session.resolve(action)} did not answer the cancel '
                  f'within {CANCEL_ANSWER_S:g} s; venting all the same', file=sys.stderr)
        elif count:
            print(f'cancelled {count} goal(s) of {session.resolve(action)}')
    session.spin_for(0.3)                       # the controller's state after the cancel
    try:
        release_holding_controller(session, setpoints.control, timeout_s)
    except CliError as error:
        print(f'pma vent: warning: {error}; venting all the same', file=sys.stderr)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            state = setpoints.command(0.0, max(1.0, deadline - time.monotonic()))
            break
        except CliError as error:
            # A cancelled sweep lets go of the device once its thread has vented.
            if 'a sweep is running' not in str(error) or time.monotonic() > deadline:
                raise
            session.spin_for(0.2)
    print(f'venting: setpoint 0 kPa taken by the device (pressure now '
          f'{q.kpa(state.gauge_pressure_pa)})')
    warning = setpoints.controller_warning()
    if warning:
        print(f'pma vent: {warning}', file=sys.stderr)
    if wait:
        state = setpoints.settle(0.0, REST_PA / 5, timeout_s)
        print(f'vented: {q.kpa(state.gauge_pressure_pa)}')
    return OK


def tare(session: Session, vent_first: bool, timeout_s: float) -> int:
    client = session.node.create_client(Trigger, f'{DRIVER}/tare')
    if vent_first:
        setpoints = Setpoints(session)
        setpoints.wait_for_driver(timeout_s)
        setpoints.command(0.0, timeout_s)
        print('venting; waiting for the pressure to settle')
        state = setpoints.steady()
        print(f'settled at {q.kpa(state.gauge_pressure_pa)}')
    response = session.call(client, Trigger.Request(), timeout_s,
                            session.where_hint(names.STATE, DRIVER), node=DRIVER)
    if not response.success:
        hint = ' (`pma tare --vent` vents and waits first)' if 'not vented' in response.message \
            else ''
        raise CliError(f'tare refused: {response.message}{hint}')
    print(response.message)
    return OK


# -- the inverse model ---------------------------------------------------------------------

BRANCH_CHOICES = {'auto': PressureForLength.Request.BRANCH_AUTO,
                  'inc': PressureForLength.Request.BRANCH_INCREASING,
                  'increasing': PressureForLength.Request.BRANCH_INCREASING,
                  'dec': PressureForLength.Request.BRANCH_DECREASING,
                  'decreasing': PressureForLength.Request.BRANCH_DECREASING}


_NUMBER = r'[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?'


def describe_inverse(answer, length_m: float, branch: str, unit: str = 'cm') -> str:
    """pressure_for_length's answer in one line, lengths in `unit` and pressures in kPa.

    The service's message is SI and names the model's inner workings (`on the mixed
    increasing path from the current state (1649.56 Pa)`: `mixed` is the blend of its
    memory rules); what a user needs of it is said in words instead: which way the pressure
    goes, and from where.
    """
    message = answer.message
    direction = BRANCHES.get(answer.branch) or (
        'increasing' if branch in ('inc', 'increasing') else
        'decreasing' if branch in ('dec', 'decreasing') else
        next(iter(re.findall(r'\b(increasing|decreasing)\b', message)), ''))
    now = re.search(rf'current state \(({_NUMBER}) Pa', message)
    if branch == 'auto' and now:
        way = 'inflating' if direction == 'increasing' else 'deflating'
        how = (f'{way} from the current {q.kpa(float(now.group(1)))}, along the path the '
               "model predicts from the muscle's history")
        there = 'that way'
    else:
        how = {'increasing': 'inflating from rest', 'decreasing': 'deflating from the top'
               }.get(direction, '')
        there = 'on that branch'
    where = f' on the {direction} branch' if direction else ''
    where += f' ({how})' if how else ''
    wanted = q.length(length_m, unit)
    if answer.success:
        return (f'{wanted}{where}: {q.kpa(answer.gauge_pressure_pa)} '
                f'({answer.gauge_pressure_pa:.0f} Pa); reachable {there}: '
                f'{q.length_range(answer.min_length_m, answer.max_length_m, unit)}')
    if not (math.isfinite(answer.min_length_m) and math.isfinite(answer.max_length_m)):
        # Refused before any range was computed (a negative length): the service's reason.
        return f'no pressure for {wanted}: {q.in_units(message, unit)}'
    top = re.search(rf'0\.\.({_NUMBER}) Pa', message)
    pressures = f' with 0 .. {q.kpa(float(top.group(1)))}' if top else ''
    return (f'no pressure gives {wanted}{where}: reachable {there} '
            f'{q.length_range(answer.min_length_m, answer.max_length_m, unit)}{pressures}')


def pressure_for_length(session: Session, length_m: float, branch: str, si: bool,
                        timeout_s: float, *, unit: str = 'cm') -> int:
    """Ask the inverse model; lengths are printed in `unit` (the one the user typed)."""
    client = session.node.create_client(PressureForLength, names.PRESSURE_FOR_LENGTH)
    request = PressureForLength.Request(length_m=length_m, branch=BRANCH_CHOICES[branch])
    answer = session.call(client, request, timeout_s,
                          session.where_hint(names.PREDICTION, 'model_node')
                          + f' Start it: {session.start_hint("model_node")}', query=True,
                          node='model_node')
    if not answer.success:
        raise CliError(describe_inverse(answer, length_m, branch, unit))
    if si:
        print(f'{answer.gauge_pressure_pa:.1f}')
        return OK
    print(describe_inverse(answer, length_m, branch, unit))
    return OK


# -- parameters ----------------------------------------------------------------------------

TYPE_NAMES = {ParameterType.PARAMETER_BOOL: 'bool', ParameterType.PARAMETER_INTEGER: 'integer',
              ParameterType.PARAMETER_DOUBLE: 'double', ParameterType.PARAMETER_STRING: 'string',
              ParameterType.PARAMETER_BYTE_ARRAY: 'byte array',
              ParameterType.PARAMETER_BOOL_ARRAY: 'bool array',
              ParameterType.PARAMETER_INTEGER_ARRAY: 'integer array',
              ParameterType.PARAMETER_DOUBLE_ARRAY: 'double array',
              ParameterType.PARAMETER_STRING_ARRAY: 'string array'}
INT64 = (-2 ** 63, 2 ** 63 - 1)     # a parameter's integer_value: more raises inside rclpy


class Parameters:
    """A node's parameter services (what `ros2 param` calls)."""

    def __init__(self, session: Session, node: str, timeout_s: float):
        self.session = session
        self.node = session.node_name(node)
        self.timeout_s = timeout_s
        make = session.node.create_client
        self._get = make(GetParameters, f'{self.node}/get_parameters')
        self._set = make(SetParameters, f'{self.node}/set_parameters')
        self._list = make(ListParameters, f'{self.node}/list_parameters')
        self._describe = make(DescribeParameters, f'{self.node}/describe_parameters')

    def _call(self, client, request, query: bool = True):
        graph = self.session.node

        def running() -> set[str]:
            return {f'{ns.rstrip("/")}/{name}'
                    for name, ns in graph.get_node_names_and_namespaces()
                    if not name.startswith('_')}

        started = time.monotonic()

        def ready_or_absent() -> bool:
            # Discovery takes a moment; after it, a node that is not in the graph is a typo or
            # another namespace, and waiting out the whole timeout would not help.
            if client.service_is_ready():
                return True
            if time.monotonic() - started < ABSENT_AFTER_S:
                return False
            nodes = running()
            return bool(nodes) and self.node not in nodes

        self.session.spin_until(ready_or_absent, self.timeout_s, waiting_for=self.node)
        if not client.service_is_ready():
            nodes = sorted(running())
            close = difflib.get_close_matches(self.node, nodes, n=1, cutoff=0.5)
            raise CliError(f'no node {self.node} answers'
                           + (f' (did you mean {close[0]}?)' if close else '')
                           + f'; nodes running: {", ".join(nodes) or "none"}', NO_ANSWER)
        return self.session.answer(client, request, self.timeout_s, query)

    def names(self) -> list[str]:
        return sorted(self._call(self._list, ListParameters.Request()).result.names)

    def get(self, name: str):
        """(value message, description) of one parameter; CliError if it has none by this name."""
        values = self._call(self._get, GetParameters.Request(names=[name])).values
        value = values[0] if values else None
        if value is None or value.type == ParameterType.PARAMETER_NOT_SET:
            close = difflib.get_close_matches(name, self.names(), n=3, cutoff=0.5)
            raise CliError(f'{self.node} has no parameter {name}'
                           + (f' (did you mean {", ".join(close)}?)' if close else
                              f'; `pma param list {self.node}` lists them'))
        return value

    def values(self, names: list[str]) -> dict:
        """Python values of these parameters (CliError naming any the node lacks)."""
        answer = self._call(self._get, GetParameters.Request(names=names)).values
        missing = names if len(answer) != len(names) else [
            n for n, v in zip(names, answer, strict=True)
            if v.type == ParameterType.PARAMETER_NOT_SET]
        if missing:
            raise CliError(f'{self.node} has no parameter(s) {", ".join(missing)}')
        return {n: parameter_value_to_python(v) for n, v in zip(names, answer, strict=True)}

    def describe(self, names: list[str]):
        return self._call(self._describe, DescribeParameters.Request(names=names)).descriptors

    def set(self, name: str, value) -> tuple[bool, str]:
        message = Parameter(name, value=value).to_parameter_msg()
        result = self._call(self._set, SetParameters.Request(parameters=[message]),
                            query=False).results[0]
        return result.successful, result.reason


def typed_value(name: str, text: str, current_type: int):
    """`text` as the type the parameter has now; units allowed where the name has one."""
    kind = q.unit_of_name(name)
    try:
        if current_type == ParameterType.PARAMETER_DOUBLE:
            q.ascii_only(text)                 # float() takes every script's digits
            if not kind:
                return float(text)
            value = q.parse(text, kind)
            slip = q.unit_slip(text, kind)     # `max_gauge_pressure_pa 450`: 450 Pa
            if slip:
                print(f'pma param: note: {slip}', file=sys.stderr)
            return value
        if current_type == ParameterType.PARAMETER_INTEGER:
            return q.parse_count(text, *INT64)
        if current_type == ParameterType.PARAMETER_BOOL:
            lowered = text.strip().lower()
            if lowered not in ('true', 'false'):
                raise ValueError('give true or false')
            return lowered == 'true'
        if current_type == ParameterType.PARAMETER_STRING:
            if name.endswith('_file') and text and not os.path.isabs(text):
                # The node resolves a relative path against its own working directory.
                return os.path.abspath(text)
            return text
        value = yaml.safe_load(text)
        if not isinstance(value, list):
            raise ValueError('give a YAML list, e.g. [1.0, 2.0]')
        if any(isinstance(v, int) and not INT64[0] <= v <= INT64[1] for v in value):
            raise ValueError(f'an integer is outside {INT64[0]} .. {INT64[1]}')
        return value
    except (ValueError, yaml.YAMLError) as error:
        raise CliError(f'{text!r} is not a valid {TYPE_NAMES.get(current_type, "value")} for '
                       f'{name}: {error}', 2) from None


def shown(name: str, value) -> str:
    """`500000.0 (500.0 kPa)`: SI as stored, the human unit beside it."""
    python = parameter_value_to_python(value)
    text = repr(python) if isinstance(python, str) else str(python).lower() \
        if isinstance(python, bool) else str(python)
    if isinstance(python, float):
        human = q.human(python, q.unit_of_name(name))
        if human:
            text += f' ({human})'
    return text


def param(session: Session, action: str, node: str, name: str | None, value: str | None, *,
          timeout_s: float) -> int:
    params = Parameters(session, node, timeout_s)
    if action == 'list':
        names = params.names()
        descriptors = {d.name: d for d in params.describe(names)}
        values = params._call(params._get, GetParameters.Request(names=names)).values
        for item, current in zip(names, values, strict=True):
            description = descriptors[item].description if item in descriptors else ''
            print(f'{item} = {shown(item, current)}' + (f'   # {description}' if description
                                                         else ''))
        return OK
    if action == 'get':
        print(f'{name} = {shown(name, params.get(name))}')
        return OK
    current = params.get(name)
    new = typed_value(name, value, current.type)
    ok, reason = params.set(name, new)
    if not ok:
        raise CliError(f'{params.node} refused {name} = {new!r}: {reason or "no reason given"}')
    print(f'{params.node}: {name} = {shown(name, params.get(name))}')
    return OK

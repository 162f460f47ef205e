"""What `pma` prints: one unit style per line (the user's length unit where they gave one,
else cm; kPa), no model jargon, nothing said before it is true, and no silent wait for a node
that is not running (issue 46). No ROS graph: the answers and the session are stand-ins."""

import time
from types import SimpleNamespace

import pytest

from pma_cli import goals
from pma_cli.commands import describe_inverse
from pma_cli.observe import NodeStatus, control_line
from pma_cli.session import WAITING_NOTE_S, Session
from pma_interfaces.msg import ControlState
from pma_interfaces.srv import PressureForLength

pytestmark = pytest.mark.in_process

INC, DEC = PressureForLength.Request.BRANCH_INCREASING, PressureForLength.Request.BRANCH_DECREASING


def answer(*, success=True, message='', pressure_pa=17819.0, branch=INC, low=0.244484,
           high=0.300383):
    return PressureForLength.Response(success=success, message=message,
                                      gauge_pressure_pa=pressure_pa, branch=branch,
                                      min_length_m=low, max_length_m=high)


def assert_one_style(line: str, unit: str) -> None:
    others = {'cm', 'mm', ' m'} - {unit if unit != 'm' else ' m'}
    assert not any(f'{other} ' in f'{line} ' or line.endswith(other) for other in others), line
    for jargon in ('mixed', 'current state', '[0.', ' Pa,', ' Pa):', ' m)'):
        assert jargon not in line, line


def test_pma_length_in_mm_says_it_in_mm_without_the_models_jargon():
    # `pma length 300mm` printed: 30.00 cm on the increasing branch: 17.8 kPa (17819 Pa;
    # reachable there: 24.45 cm .. 30.04 cm); on the mixed increasing path from the current
    # state (1649.56 Pa)
    line = describe_inverse(answer(message='on the mixed increasing path from the current '
                                           'state (1649.56 Pa)'), 0.3, 'auto', 'mm')
    assert line == ('300.0 mm on the increasing branch (inflating from the current 1.6 kPa, '
                    "along the path the model predicts from the muscle's history): 17.8 kPa "
                    '(17819 Pa); reachable that way: 244.5 .. 300.4 mm')
    assert_one_style(line, 'mm')


def test_a_major_branch_answer_says_which_way_the_pressure_goes():
    line = describe_inverse(answer(message='on the mixed decreasing major branch', branch=DEC,
                                   pressure_pa=91673.0), 0.29, 'dec')
    assert line.startswith('29.00 cm on the decreasing branch (deflating from the top): '
                           '91.7 kPa (91673 Pa); reachable on that branch: 24.45 .. 30.04 cm')
    assert_one_style(line, 'cm')


def test_an_unreachable_length_gives_the_range_in_the_users_unit():
    message = ('length 0.2 m is not reachable on the mixed increasing path from the current '
               'state (1038.61 Pa): reachable [0.244484, 0.300383] m with 0..500000 Pa')
    refused = answer(success=False, message=message, branch=0, pressure_pa=float('nan'))
    line = describe_inverse(refused, 0.2, 'auto', 'cm')
    assert line == ('no pressure gives 20.00 cm on the increasing branch (inflating from the '
                    "current 1.0 kPa, along the path the model predicts from the muscle's "
                    'history): reachable that way 24.45 .. 30.04 cm with 0 .. 500.0 kPa')
    assert_one_style(line, 'cm')
    assert describe_inverse(refused, 0.2, 'auto', 'm').startswith('no pressure gives 0.2000 m')


def test_a_refusal_without_a_range_keeps_the_services_reason():
    refused = answer(success=False, message='length_m must be positive (metres), got -0.03',
                     branch=0, low=float('nan'), high=float('nan'))
    assert describe_inverse(refused, -0.03, 'auto') == (
        'no pressure for -3.00 cm: length_m must be positive (metres), got -0.03')


def test_status_shows_the_held_length_in_cm_as_the_rest_of_its_line():
    # `pma status` showed "holding 0.2750 m" beside "target 27.50 cm".
    status = NodeStatus('length_controller', 'length control', 'OK', 'holding 0.2750 m', {})
    control = ControlState(mode=ControlState.MODE_HOLD, target_length_m=0.275,
                           gauge_pressure_command_pa=171_500.0)
    line = control_line(status, control)
    assert line == ('control   OK holding 27.50 cm | mode hold | target 27.50 cm, command '
                    '171.5 kPa')
    released = ControlState(mode=ControlState.MODE_IDLE, message='hold ended: released: '
                            'another node commanded 60000 Pa on pma/pressure_setpoint')
    assert control_line(None, released).endswith('another node commanded 60.0 kPa on '
                                                 'pma/pressure_setpoint')


def run_move(monkeypatch, capsys, *, feedback: list, success: bool, message: str,
             unit: str = 'cm', length_m: float = 0.4):
    """goals.move against a stand-in goal: `feedback` is sent, then the result."""
    def fake_run_goal(session, action_type, name, goal, *, on_feedback, **kwargs):
        for item in feedback:
            on_feedback(item)
        result = SimpleNamespace(success=success, message=message, settle_time_s=0.7,
                                 measured_length_m=0.3012, estimated_length_m=0.3013)
        return (4 if success else 6), result, False

    monkeypatch.setattr(goals, 'run_goal', fake_run_goal)
    session = SimpleNamespace(where_hint=lambda *args: '')
    code = goals.move(session, length_m=length_m, tolerance_m=0.0, settle_s=0.0,
                      goal_timeout_s=0.0, timeout_s=1.0, unit=unit)
    return code, capsys.readouterr()


def test_a_refused_move_never_says_it_is_moving(monkeypatch, capsys):
    # `pma move 40cm` printed "moving to 40.00 cm", then the refusal.
    code, out = run_move(monkeypatch, capsys, feedback=[], success=False,
                         message='target 0.4000 m is not reachable: reachable [0.2454, '
                                 '0.3008] m with 0..500000 Pa')
    assert code == 1 and out.out == ''
    assert out.err == ('move aborted: target 40.00 cm is not reachable: reachable 24.54 .. '
                       '30.08 cm with 0.0 .. 500.0 kPa (measured 30.12 cm, estimated 30.13 cm)\n')


def test_a_move_says_moving_once_the_controller_follows_it_in_the_users_unit(monkeypatch,
                                                                              capsys):
    step = SimpleNamespace(estimated_length_m=0.29, error_m=-0.02,
                           gauge_pressure_command_pa=100_000.0)
    code, out = run_move(monkeypatch, capsys, feedback=[step, step], success=True,
                         message='settled within 2.0 mm for 1 s after 0.70 s; holding',
                         unit='mm', length_m=0.27)
    assert code == 0
    assert out.out.splitlines() == [
        'moving to 270.0 mm',
        'move succeeded: settled within 2.0 mm for 1 s after 0.70 s; holding (measured '
        '301.2 mm, estimated 301.3 mm, settled after 0.7 s)']


class StandInSession:
    """What Session.spin_until uses, without a ROS node: a graph of `nodes`."""

    def __init__(self, nodes=(), namespace='/', up=True):
        self.stop = SimpleNamespace(is_set=lambda: False)
        self.verb, self.up, self.namespace = 'move', up, namespace
        self._waiting_said = set()
        self.node = SimpleNamespace(get_node_names_and_namespaces=lambda: list(nodes))
        self.executor = SimpleNamespace(spin_once=lambda timeout_sec: time.sleep(timeout_sec))  # noqa: PLW0108

    node_name = Session.node_name
    running = Session.running
    start_hint = Session.start_hint
    waiting_note = Session.waiting_note
    _elsewhere = Session._elsewhere
    spin_until = Session.spin_until


def test_a_wait_for_a_node_that_is_not_running_says_so_after_a_second(capsys):
    # `pma move` with no controller waited 10 s without a word.
    session = StandInSession(nodes=[('driver_node', '/'), ('length_controller', '/left')])
    started = time.monotonic()
    assert not session.spin_until(lambda: False, WAITING_NOTE_S + 0.3,
                                  waiting_for='length_controller')
    err = capsys.readouterr().err
    assert err == ('pma move: waiting for length_controller in / (not seen yet): is it running? '
                   '(`pma up`, or `pma run pma_control length_controller`) It runs in /left: '
                   'add --namespace left.\n')
    assert time.monotonic() - started >= WAITING_NOTE_S


def test_no_note_for_a_node_in_the_graph_or_a_wait_that_ends_first(capsys):
    session = StandInSession(nodes=[('driver_node', '/')])
    session.spin_until(lambda: False, WAITING_NOTE_S + 0.2, waiting_for='driver_node')
    StandInSession().spin_until(lambda: True, 5.0, waiting_for='driver_node')
    assert capsys.readouterr().err == ''


def test_how_to_start_each_node_in_its_namespace():
    left = StandInSession(namespace='/left')
    assert Session.start_hint(left, 'driver_node') == (
        '`pma up --namespace left`, or `pma run pma_driver driver_node --ros-args -r '
        '__ns:=/left -p port:=/dev/pma0`')
    assert Session.start_hint(StandInSession(up=False), 'model_node') == \
        '`pma run pma_model model_node`'
    assert Session.start_hint(left, 'recorder_day2') == ''

"""`pma up`: one muscle's nodes, what bringup.launch.py starts, without `ros2 launch`.

The processes come from pma_bringup.node_set (the launch file's own list) and are started
as `ros2 run` starts them, each in a session of its own with its log in the run directory
(runs/<timestamp>/logs/<name>.log, as the demo's). `pma up` waits until the driver streams
pma/state, the model predicts (pma/prediction) and every node is in the graph, prints a
ready line, then watches them: a process that ends while up is reported (its exit code and
its log's last lines) and the rest are stopped (exit 1). Ctrl-C, SIGTERM or SIGHUP (a
closed terminal) stops them all in order (node_set.stop_order: the controller, then the
driver, which vents, then the rest, the simulated device last), each SIGINT -> SIGTERM ->
SIGKILL with a deadline. Should `pma up`
itself be killed, each process gets SIGTERM from the kernel (PR_SET_PDEATHSIG) and stops.

Exit codes: 0 stopped cleanly after it was up, 1 a process failed to come up, ended while
up or had to be killed, 2 bad arguments, 130 stopped before the rig was up.
"""

from __future__ import annotations

import datetime
import os
import shlex
import signal
import sys
import time
from pathlib import Path

from pma_bringup.node_set import NodeSpec, Options, node_set, stop_order
from pma_cli.session import FAILED, INTERRUPTED, OK, USAGE, CliError, Interrupted
from pma_common import experiment, names
from pma_common.commands import ExecutableNotFoundError, installed_executable
from pma_common.processes import STOP_STEPS, Child, start_child, stop_children

LOG_TAIL_LINES = 15
POLL_S = 0.2


def _absolute(path: Path | None) -> str:
    return '' if path is None else str(path.expanduser().absolute())


def options_from_args(args) -> Options:
    """`pma up`'s flags as node_set's Options (the same as bringup.launch.py's arguments)."""
    return Options(
        namespace=args.namespace.strip('/'), port=args.port, simulated=args.simulated,
        fake_arduino_seed=args.seed, driver=not args.no_driver, model=not args.no_model,
        control=not args.no_control,
        record=args.record is not None,
        bag_dir='' if not args.record else _absolute(Path(args.record)),
        live=args.live, live_host=args.live_host, live_port=args.live_port,
        driver_params_file=_absolute(args.driver_params),
        model_params_file=_absolute(args.model_params),
        control_params_file=_absolute(args.control_params),
        recorder_params_file=_absolute(args.recorder_params),
        refit_params_file=_absolute(args.refit_params),
        experiment={**experiment.typed(args), 'note': args.note})


def command(spec: NodeSpec) -> list[str]:
    """The argv `ros2 run PKG EXE ARGS --ros-args ...` would execute for `spec`."""
    try:
        path = installed_executable(spec.package, spec.executable)
    except ExecutableNotFoundError as error:
        raise CliError(str(error), USAGE) from None
    return [str(path), *spec.arguments, *spec.ros_arguments()]


def commands(options: Options) -> list[tuple[NodeSpec, list[str]]]:
    return [(spec, command(spec)) for spec in node_set(options)]


class Output:
    """Prints, and the same lines in up.log; a terminal that went away (SIGHUP: writes
    fail with EIO) is let go, and the log goes on."""

    def __init__(self, log_path: Path):
        self.log = open(log_path, 'a', buffering=1)

    def say(self, text: str, error: bool = False) -> None:
        self.log.write(text + '\n')
        stream = sys.stderr if error else sys.stdout
        try:
            print(text, file=stream, flush=True)
        except OSError:
            devnull = open(os.devnull, 'w')      # for the rest of the process
            sys.stdout = sys.stderr = devnull


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f'was killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'was killed by signal {-code}'
    return f'ended with exit code {code}'


def tail(path: Path, lines: int = LOG_TAIL_LINES) -> str:
    try:
        text = path.read_text(errors='replace').splitlines()[-lines:]
    except OSError:
        return '    (no log)'
    return '\n'.join(f'    | {line}' for line in text) or '    (the log is empty)'


class Rig:
    """The processes of one `pma up`, started in node_set's order, stopped in stop_order's."""

    def __init__(self, run_dir: Path, out: Output):
        self.run_dir = run_dir
        self.logs = run_dir / 'logs'
        self.out = out
        self.children: list[Child] = []
        self.specs: dict[str, NodeSpec] = {}

    def start(self, spec: NodeSpec, argv: list[str]) -> Child:
        # Started before this process has a second thread (rclpy comes later).
        child = start_child(spec.name, argv, log_path=self.logs / f'{spec.name}.log',
                            env=spec.env, die_with_parent=True)
        self.specs[spec.name] = spec
        self.children.append(child)
        self.out.log.write(f'{spec.name} (pid {child.pid}): {shlex.join(argv)}\n')
        return child

    def ended(self) -> list[Child]:
        return [child for child in self.children if child.popen.poll() is not None]

    def report_ended(self, child: Child, while_what: str) -> None:
        self.out.say(f'pma up: {child.name} (pid {child.popen.pid}) '
                     f'{describe_exit(child.popen.returncode)} {while_what}; its log '
                     f'({child.log_path}) ends:\n{tail(child.log_path)}', error=True)

    def stop(self) -> bool:
        """Stop every process, stage by stage; True if each ended at its SIGINT, with 0."""
        by_name = {child.name: child for child in self.children}
        clean = True
        for stage in stop_order([self.specs[child.name] for child in self.children]):
            clean &= self._stop_together([by_name[spec.name] for spec in stage])
        return clean

    def _stop_together(self, children: list[Child]) -> bool:
        running = [child for child in children if child.popen.poll() is None]
        ended_before = [child for child in children if child not in running]
        started = time.monotonic()
        escalated = []

        def escalating(still_running: list[Child], sig: int) -> None:
            escalated.append(sig)
            self.out.say(f'pma up: {", ".join(c.name for c in still_running)} still running: '
                         f'sending {signal.Signals(sig).name}', error=True)

        stop_children(running, STOP_STEPS, escalating)
        clean = not escalated
        for child in children:
            code = child.popen.poll()
            if child in ended_before:            # reported when it ended
                self.out.say(f'   {child.name} had ended already ({describe_exit(code)})')
            elif code is None:
                clean = False
                self.out.say(f'pma up: {child.name} (pid {child.popen.pid}) did not end even '
                             'at SIGKILL', error=True)
            else:
                clean &= code == 0
                note = ''
                if self.specs[child.name].lifecycle:     # the driver: did it say it vented?
                    vented = 'vented' in ''.join(tail(child.log_path, 5))
                    note = ' (it vented)' if vented else ' (its log does not say it vented)'
                self.out.say(f'   stopped {child.name}: {describe_exit(code)} after '
                             f'{time.monotonic() - started:.1f} s{note}')
        return clean


def make_run_dir(runs_dir: Path, namespace: str) -> Path:
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    stem = f'{stamp}-{namespace.replace("/", "_")}' if namespace else stamp
    for attempt in range(1, 100):
        run_dir = (runs_dir / (stem if attempt == 1 else f'{stem}-{attempt}')).absolute()
        try:
            (run_dir / 'logs').mkdir(parents=True)
            return run_dir
        except FileExistsError:
            continue
    raise CliError(f'cannot make a run directory under {runs_dir}')


def wait_until_up(rig: Rig, options: Options, timeout_s: float, stop) -> str:
    """Until the driver streams pma/state, the model predicts and every node is in the
    graph: a line about the first sample. CliError (what did not come up, and its log) at
    the deadline or when a process ends; Interrupted at a stop signal."""
    from pma_cli.session import Session
    from pma_common.node import init_without_signal_handlers
    from pma_interfaces.msg import PmaPrediction, PmaState

    init_without_signal_handlers([])
    import rclpy
    session = Session(options.namespace, stop)
    try:
        state = session.latest(PmaState, names.STATE)
        prediction = session.latest(PmaPrediction, names.PREDICTION)
        wanted = {child.name for child in rig.children if rig.specs[child.name].ros}
        namespace = session.namespace

        def in_graph() -> set[str]:
            return {name for name, ns in session.node.get_node_names_and_namespaces()
                    if ns == namespace} & wanted

        def all_up() -> bool:
            # Without --no-driver or --no-model here, another computer's (docs/lab-network.md).
            return (state.message is not None
                    and (prediction.message is not None or not options.model)
                    and in_graph() == wanted)

        session.spin_until(lambda: bool(rig.ended()) or all_up(), timeout_s)
        if rig.ended():
            child = rig.ended()[0]
            rig.report_ended(child, 'while coming up')
            raise CliError(f'{child.name} did not come up')
        if all_up():
            sample = state.message
            return (f'{sample.gauge_pressure_pa / 1e3:.1f} kPa, {sample.length_m * 100:.2f} cm')
        missing = []
        if state.message is None:
            why = ''
            if not options.driver:
                why = ' (--no-driver: is it running on the rig computer, in this ROS domain?)'
            elif not options.simulated and not Path(options.resolved_port()).exists():
                why = f' (there is no {options.resolved_port()}: is the rig plugged in? '
                why += 'the driver retries it every second)'
            missing.append(f'driver_node: no pma/state within {timeout_s:g} s{why}')
        elif prediction.message is None and options.model:
            missing.append(f'model_node: no pma/prediction within {timeout_s:g} s')
        for name in sorted(wanted - in_graph()):
            missing.append(f'{name}: not in the graph (namespace {namespace})')
        logs = {line.split(':')[0] for line in missing}
        details = '\n'.join(f'  {line}' for line in missing)
        for name in sorted(logs & {child.name for child in rig.children}):
            child = next(c for c in rig.children if c.name == name)
            details += f'\n  {name}\'s log ({child.log_path}) ends:\n{tail(child.log_path)}'
        if options.simulated and options.driver and 'driver_node' in logs:
            fake = next(c for c in rig.children if c.name == 'fake_arduino')
            details += f'\n  fake_arduino\'s log ({fake.log_path}) ends:\n{tail(fake.log_path)}'
        raise CliError(f'the rig did not come up within {timeout_s:g} s:\n{details}')
    finally:
        session.close()
        rclpy.try_shutdown()


def main(args) -> int:
    from pma_common.stop import stop_request
    stop = stop_request()
    options = options_from_args(args)
    try:
        experiment.from_arguments(args)         # a --load-kg that is no number, ...
        planned = commands(options)
    except ValueError as error:                         # a live port outside 0..65535
        print(f'pma up: {error}', file=sys.stderr)
        return USAGE
    except CliError as error:                           # an executable not installed
        print(f'pma up: {error}', file=sys.stderr)
        return error.code
    run_dir = make_run_dir(args.runs_dir, options.namespace)
    out = Output(run_dir / 'up.log')
    rig = Rig(run_dir, out)
    ns_flag = f' --namespace {options.namespace}' if options.namespace else ''
    out.say(f'pma up: run directory {run_dir}')
    code = FAILED
    try:
        for spec, argv in planned:
            if stop.is_set():
                raise Interrupted(stop.reason)
            child = rig.start(spec, argv)
            out.say(f'   {spec.name:18s} pid {child.popen.pid:<7d} log {child.log_path}')
        where = ('the simulated rig at ' if options.simulated else 'port ')
        where += options.resolved_port()
        out.say(f'pma up: waiting for the driver to stream ({where}; at most {args.wait:g} s)')
        started = time.monotonic()
        first = wait_until_up(rig, options, args.wait, stop)
        out.say(f'pma up: ready in {time.monotonic() - started:.1f} s: driver_node streams '
                f'pma/state ({first}); {", ".join(c.name for c in rig.children)} up')
        out.say(f'   next: pma status{ns_flag}; pma sweep{ns_flag} --max 500kPa --step 50kPa '
                '--hold 5s; pma move 27cm; Ctrl-C stops every process (the driver vents)')
        code = OK
        while not stop.wait(POLL_S):
            ended = rig.ended()
            if ended:
                for child in ended:
                    rig.report_ended(child, 'while up')
                out.say('pma up: stopping the rest', error=True)
                code = FAILED
                break
        if stop.is_set():
            out.say(f'pma up: {stop.reason}: stopping every process '
                    '(the controller, then the driver, which vents, then the rest)')
    except Interrupted as interrupted:
        out.say(f'pma up: {interrupted}: interrupted before the rig was up; stopping '
                'every process', error=True)
        code = INTERRUPTED
    except CliError as error:
        out.say(f'pma up: {error}', error=True)
        out.say('pma up: stopping every process', error=True)
        code = FAILED
    finally:
        stop.ignore_further()        # the stop runs whole, whatever arrives meanwhile
        clean = rig.stop()
    if not clean and code == OK:
        code = FAILED
    out.say(f'pma up: {"every process stopped" if clean else "stopped, not all cleanly"}; '
            f'logs in {rig.logs} (exit {code})')
    return code

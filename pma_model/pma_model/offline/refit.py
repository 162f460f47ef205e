"""`ros2 run pma_model refit <bag or csv>`: refit the hysteresis models offline.

Prints the paper-style table (kPa, cm) on stdout; --json writes the full report, --params-out
the params file model_node loads (the best-AICc branch form it supports, or --model), --plots
the paper's Figs. 6-8, the time series and the minor loops; the JSON and every figure say
which run (--run-id), when, by which software, and carry the bag's metadata. Bad input
gives one line on stderr and exit code 2. A model that does not converge is reported as
failed (table and JSON) and the others stand; the exit code is 2 only when the model asked
for with --model, or every branch model --params-out could use, failed. A truncated bag is
refitted on what it holds before the damage, with a warning line.

Before it trusts a fit, refit checks what it fitted (pma_model.offline.checks: a level near 0
kPa on the increasing branch and near the top on the decreasing one, each level on the branch
its place in the sweep says, the fitted L0 against the lengths measured at rest, enough levels
for the parameters, the sweep's own `settled` verdicts): each warning is printed, kept in the
JSON (`data_checks`), drawn on the loop figure and written at the top of the params file. With
--strict a warning is an error: exit 3 and no params file.

The console gets a summary (the run's Table 2, the warnings, the outputs); --verbose adds
every model's parameters, the whole loop, the hold-out and the memory rules in full.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from pma_common.commands import run_command
from pma_common.console import closed_pipe_ends_quietly
from pma_model.detector import DEFAULT_DEADBAND_PA
from pma_model.offline.provenance import input_run
from pma_model.offline.report import (
    BRANCH_MODEL_FORMS,
    FORM_MODELS,
    MIN_POINTS_PER_BRANCH,
    MODEL_NAMES,
    ONLINE_MEMORIES,
    build_report,
    data_checks,
    failed_models,
    format_summary,
    format_table,
    memory_check,
)
from pma_model.offline.samples import STATE_TOPIC, SamplesError, load_fit_input, load_samples
from pma_model.params import MEMORIES

EXIT_BAD_INPUT = 2
EXIT_STRICT = 3     # --strict and the data checks warned (or the bag is truncated)


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog='refit', description='Refit the PMA hysteresis models to a bag or CSV and report '
        "the paper's statistics.")
    parser.add_argument('input', type=Path,
                        help='rosbag2 MCAP bag (directory or .mcap) with PmaState on pma/state, '
                        'a CSV sample log (time_s,gauge_pressure_pa,length_m[,gauge_setpoint_pa])'
                        ' or a branch table (pressure_kpa,length_increasing_cm,'
                        'length_decreasing_cm)')
    parser.add_argument('--json', type=Path, metavar='FILE', help='write the report as JSON')
    parser.add_argument('--params-out', type=Path, metavar='FILE.yaml',
                        help='write a model_node params file with the chosen branch model')
    parser.add_argument('--plots', type=Path, metavar='DIR', help='write PNG figures here')
    parser.add_argument('--run-id', metavar='ID',
                        help='the run these data belong to, in the JSON and on every figure '
                        "(default: the bag's custom_data run_id, else the input's name)")
    parser.add_argument('--model', choices=sorted(BRANCH_MODEL_FORMS),
                        help='branch model for --params-out (default: best loop AICc)')
    parser.add_argument('--steady-state', action=argparse.BooleanOptionalAction, default=None,
                        help='reduce each hold to its steady-state mean (default: when the '
                        'data are mostly holds)')
    parser.add_argument('--deadband-pa', type=float, default=DEFAULT_DEADBAND_PA, metavar='X',
                        help=f'branch detector deadband [Pa] (default {DEFAULT_DEADBAND_PA:g})')
    parser.add_argument('--memory-check', type=Path, metavar='BAG_OR_CSV',
                        help=f'also run each memory ({", ".join(MEMORIES)}) '
                        'with the fitted branches along this recorded path (minor loops, e.g. '
                        'a Sweep with reversal_pressures_pa) and score it; mix and identify '
                        'learn online as model_node does; --params-out then also sets memory '
                        'to the best (and, for mix or identify, what they learned)')
    parser.add_argument('--topic', default=STATE_TOPIC,
                        help='PmaState topic of a bag (default: pma/state in any namespace)')
    parser.add_argument('--no-holdout', action='store_true',
                        help='skip the interleaved hold-out refits')
    parser.add_argument('--strict', action='store_true',
                        help='a data-check warning (or a truncated bag) is an error: exit '
                        f'{EXIT_STRICT} and no --params-out file (the JSON and plots are '
                        'still written)')
    parser.add_argument('--verbose', '-v', action='store_true',
                        help='print every model\'s parameters, the whole loop, the hold-out '
                        'and the memory rules in full, and every model warning')
    args = parser.parse_args(argv)
    if not args.deadband_pa >= 0:
        parser.error('--deadband-pa must be >= 0')
    return args


def choose_params_model(report: dict, requested: str | None) -> str | None:
    """The requested model, else the fitted branch model of best loop AICc (None: none)."""
    if requested:
        return requested
    loop = {name: entry for name, entry in report['loop']['models'].items()
            if name in BRANCH_MODEL_FORMS and 'error' not in entry}
    scored = [(entry['metrics']['aicc'], name) for name, entry in loop.items()
              if entry['metrics']['aicc'] is not None]
    if not scored:  # AICc needs n > k + 1; fall back on AIC
        scored = [(entry['metrics']['aic'], name) for name, entry in loop.items()]
    return min(scored)[1] if scored else None


def write_params(path: Path, fitted, name: str, source: str, memory: str | None = None, *,
                 identified: dict | None = None, warnings: list[str] = ()) -> None:
    """The branch form and the fitted branches (and the memory rule, if one was measured).

    With memory 'mix' or 'identify', what the online identification learned along the
    memory-check path (`identified`: play shares, branch corrections, creep gains, the mix's
    weights) is written too, so model_node starts from there.

    Adaptation, deadband and the pressure limit are the node's own settings: a hot reload
    of this file must not reset them. Both forms are written (the sigmoid from the paper's
    fixed-c fit unless the free-c one was chosen), so switching `branch_form` later also
    uses this refit. `warnings` (the data checks') go at the top of the file as comments:
    a model fitted to data refit warned about never looks like any other.
    """
    from pma_model.params import default_params

    params = default_params()
    for form, model_name in FORM_MODELS.items():
        chosen = name if BRANCH_MODEL_FORMS[name] == form else model_name
        if chosen in fitted:
            branches = fitted[chosen].branches
            params = params.with_branches(branches['increasing'], branches['decreasing'])
    params = replace(params, branch_form=BRANCH_MODEL_FORMS[name])
    only = ('branch_form', 'increasing', 'decreasing')
    note = f'model {name} (branch_form {params.branch_form})'
    if memory:
        params = replace(params, memory=memory)
        only += ('memory',)
        note += f', memory {memory} (the best along the --memory-check path)'
    if memory in ONLINE_MEMORIES and identified:
        params = replace(params, identification=replace(params.identification, **identified))
        only += tuple(f'identification.{key}' for key in identified)
        note += ', with what it learned there'
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ''
    if warnings:
        header = (f'WARNING: refit warned about the data this model was fitted to '
                  f'({len(warnings)}; refit.json "data_checks"):\n'
                  + ''.join(f'  - {text}\n' for text in warnings)
                  + 'Check the sweep (or run it again from rest) before trusting this model; '
                  'refit --strict does not write it.\n\n')
    params.save_yaml(path, only=only, header=header + (
        f'Written by refit from {source}: {note}.\n'
        'Only these parameters: model_node keeps its other settings when it loads this.'))


def check_data(data) -> None:
    # With the steady-state reduction a point is a held level, not a sample: a quick ramp
    # up and down has samples on both branches and still no held level on one of them.
    points = 'held levels' if data.steady_state else 'points'
    advice = ('a staircase up and back down, e.g. pma sweep --max 500kPa --step 100kPa '
              '--hold 1s' if data.steady_state else 'a sweep up and back down')
    for direction, size in (('increasing', data.inc_pressure_pa.size),
                            ('decreasing', data.dec_pressure_pa.size)):
        if size < MIN_POINTS_PER_BRANCH:
            raise SamplesError(f'{data.source}: {size} {direction} {points}; a refit needs at '
                               f'least {MIN_POINTS_PER_BRANCH} per branch: {advice}')


def plotted_choice(report: dict, name: str | None,
                   params_written: bool) -> tuple[str | None, str]:
    """The model the loop figure shows as chosen, and why: the one written to params-out,
    else the one asked for, else (none asked for, or it failed) what --params-out would
    write; with its best memory rule when a memory check ran."""
    if name is not None and name not in failed_models(report):
        note = 'written to params-out' if params_written else 'asked for with --model'
    else:
        name, note = choose_params_model(report, None), 'best loop AICc: what params-out takes'
    rule = report.get('memory_check', {}).get('best_memory', {}).get(name)
    return name, note + (f', memory {rule}' if rule else '')


@closed_pipe_ends_quietly
def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return run(args)
    except KeyboardInterrupt:
        print('refit: interrupted; files it had not finished are not written', file=sys.stderr)
        return 130


def warn_if_truncated(what) -> None:
    """One line for a bag cut short (Samples or BranchData), instead of a Python warning."""
    if what.truncated:
        print(f'refit: warning: {what.source} is truncated ({what.truncated}); using the '
              'samples recorded before the damage (a closed copy: '
              f'{run_command("pma_bag", "recover", what.source)})', file=sys.stderr)


def unwritable_output(args: argparse.Namespace) -> str:
    """Why an output could not be written ('' when each can), found before the fits: a
    refit takes seconds to minutes, and a typo in a path should not cost them."""
    folders = [path.parent for path in (args.json, args.params_out) if path is not None]
    folders += [args.plots] if args.plots is not None else []
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as error:
            return f'cannot write to {folder}: {error.strerror or error}'
    return ''


def end_progress(progress: list) -> None:
    """End the one progress line (without --verbose), once, before anything else on stderr."""
    if progress:
        print(file=sys.stderr, flush=True)
        progress.clear()


def run(args: argparse.Namespace) -> int:
    progress: list[str] = []    # models announced on the open progress line
    reason = unwritable_output(args)
    if reason:
        print(f'refit: {reason}', file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        data, samples = load_fit_input(args.input, args.deadband_pa, args.steady_state,
                                       args.topic)
        warn_if_truncated(data)
        check_data(data)
        path = None
        if args.memory_check:      # read (or refused) before the fits, for the same reason
            path = load_samples(args.memory_check, args.topic)
            warn_if_truncated(path)

        def announce(name):
            if args.verbose:
                print(f'fitting {name} ...', file=sys.stderr, flush=True)
            else:   # one line of progress, not one per model
                print(f'fitting {name} ...' if not progress else f' {name} ...',
                      end='', file=sys.stderr, flush=True)
                progress.append(name)

        report, fitted = build_report(data, MODEL_NAMES, holdout=not args.no_holdout,
                                      on_model=announce)
        report['data_checks'] = data_checks(data, samples, fitted, args.deadband_pa)
        made = datetime.datetime.now(datetime.timezone.utc)    # one date for every output
        provenance = input_run(args.input, args.run_id, made)
        report['run'] = {k: v for k, v in provenance.items() if k != 'custom_data'}
        if provenance['custom_data']:
            report['custom_data'] = provenance['custom_data']   # the bag's metadata.yaml
        memory_run = None
        predictions: dict = {}
        if path is not None:
            announce(f'the memory rules along {args.memory_check}')
            report['memory_check'] = memory_check(path, fitted, args.deadband_pa,
                                                  predictions if args.plots else None)
            memory_run = input_run(args.memory_check, provenance['run_id'], made)
            report['memory_check']['recorded'] = memory_run['recorded']
            if memory_run['custom_data']:
                report['memory_check']['custom_data'] = memory_run['custom_data']
        end_progress(progress)
    except SamplesError as error:
        end_progress(progress)
        print(f'refit: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except (ValueError, RuntimeError) as error:
        end_progress(progress)
        print(f'refit: the fit did not converge: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.verbose:
        print(format_table(report) + '\n')
    print(format_summary(report))
    data_warnings = [f"{w['check']}: {w['message']}" for w in
                     report['data_checks']['warnings']]
    if data.truncated:
        data_warnings.append(f'truncated: {data.source} is truncated ({data.truncated})')
    failed = failed_models(report)
    name = choose_params_model(report, args.model) if args.params_out or args.model else None
    refusal = None
    if len(failed) == len(MODEL_NAMES):
        refusal = 'no model converged: ' + '; '.join(f'{n}: {e}' for n, e in failed.items())
    elif name is None and args.params_out:
        refusal = (f'no branch model converged ({", ".join(sorted(BRANCH_MODEL_FORMS))}); '
                   f'{args.params_out} not written')
    elif name in failed:
        refusal = (f'{name}, the model asked for with --model, did not converge: '
                   f'{failed[name]}' + (f'; {args.params_out} not written'
                                        if args.params_out else ''))
    strict_refusal = None
    if args.strict and data_warnings:
        strict_refusal = (f'--strict: {len(data_warnings)} data warning'
                          f'{"s" if len(data_warnings) > 1 else ""} (above)'
                          + (f'; {args.params_out} not written' if args.params_out else ''))
    try:
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(report, indent=2, allow_nan=False) + '\n')
            print(f'wrote {args.json}')
        params_written = (args.params_out is not None and refusal is None
                          and strict_refusal is None)
        if params_written:
            check = report.get('memory_check', {})
            memory = check.get('best_memory', {}).get(name)
            write_params(args.params_out, fitted, name, str(args.input), memory,
                         identified=check.get('identified', {}).get(name),
                         warnings=data_warnings)
            print(f'wrote {args.params_out} ({name}, branch_form '
                  f'{BRANCH_MODEL_FORMS[name]}'
                  + (f'; marked: fitted to data with {len(data_warnings)} warning'
                     f'{"s" if len(data_warnings) > 1 else ""}' if data_warnings else '')
                  + ')')
        if args.plots:
            chosen, note = plotted_choice(report, name, params_written)
            from pma_model.offline.plots import write_plots

            figures = write_plots(
                data, fitted, args.plots, run=provenance, chosen=chosen, chosen_note=note,
                samples=samples,
                memory=report.get('memory_check'), memory_samples=path,
                memory_run=memory_run, predictions=predictions, warnings=data_warnings)
            if args.verbose:
                for written in figures:
                    print(f'wrote {written}')
            else:
                print(f'wrote {len(figures)} figures to {args.plots}: '
                      + ', '.join(Path(written).name for written in figures))
    except (OSError, ValueError) as error:
        print(f'refit: cannot write output: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if refusal:
        print(f'refit: {refusal}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if strict_refusal:
        print(f'refit: {strict_refusal}', file=sys.stderr)
        return EXIT_STRICT
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""The model on every simulated muscle family: minor-loop errors and the issue's criteria.

Run: nice python bench/bench_memory_families.py [--seeds 1 2] [--forms sigmoid hill]
[--rate-hz 20 [50]] [--against-switch --seeds 1 2 3 4 5 6 7 8 [--jobs 2]
[--noise-free-pressure] [--kinds sines damped]] [--set tuning|validation|both]
(OMP_NUM_THREADS=1; about 11 minutes a branch form on one core, five muscles). Prints the
tables of docs/model-history.md, "The family bench in detail" (family x rule x adaptation,
RMSE and max error in cm and % of stroke) and checks, for every family (the simulator's and
the Bouc-Wen muscle of
pma_sim.evaluation), path and seed:
  - the default memory ('mix': mix.RuleMix, identify and play mixed), from the
    third reversal on: RMSE <= 0.9x and max <= 0.7x the paper's switch;
  - the mix vs the best single fixed rule (static and with the same learning): <= 1.1x RMSE;
  (the same for identify alone, the default before the mix);
  - adaptation on vs off without drift: <= 1.05x RMSE;
  - with drift (from 60 s, time constant 30 s): error back to the noise floor (<= 1.1x)
    in the window 120-240 s after the drift started. The floor is what a perfect drift
    correction of the unadapted model would leave (pma_sim.evaluation
    .perfectly_corrected): the stroke grew 8 %, so the same shape error is 1.08x the
    drift-free error in metres; both ratios are printed;
  - the moonshot: minor-loop RMSE <= 1.5 % of stroke.
Beside them, the oracle: the muscle itself made to keep return-point memory (what a model
with that property, knowing the muscle exactly, would err; 0 on a muscle that has it;
pma_sim.evaluation.return_point_oracle), as its max error over the switch's.
--against-switch scores the default and the switch alone (a few minutes for eight seeds
on two cores, where the full table takes hours) and says, for each run, when the default
errs most and how much the oracle errs at that moment: a miss where the oracle misses too
is the price of return-point memory, not of what the model has learned. With
--noise-free-pressure both read the true pressure instead of the sensor's: what is left of
a miss without the pressure reading's noise (a diagnosis; no rig has that reading). With
--kinds it runs other paths: `sines` and `damped` are smooth (no holds, slowing into every
reversal; pma_sim.paths.smooth_path), a way of driving the rig the defaults were not
chosen on.
--set runs the families and seeds of a set declared in pma_sim.splits instead of --families
(each set apart with `both`): the tuning set, on which the defaults may be chosen, or the
validation set, run only to report; with --against-switch it adds issue 47's targets for the
set (at least 90 % of runs meet both switch criteria, mean minor-loop RMSE at most 1.5 % of
stroke). The acceptance table of both sets at both rates (docs/model.md §3.1):
  nice python bench/bench_memory_families.py --against-switch --forms sigmoid \
      --set both --rate-hz 20 50
The figures are model errors (not speeds), so no in-run baseline is needed; the reference
is the paper's switch on the same samples.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from pma_sim import splits
from pma_sim.evaluation import (
    ALL_CONFIGS,
    ALL_PATH_KINDS,
    DEFAULT_RATE_HZ,
    IDENTIFY,
    LEARNED_RULES,
    MIXED,
    PAPER,
    PATH_KINDS,
    SCORED_FAMILIES,
    STATIC_RULES,
    STROKE_M,
    Config,
    Scenario,
    oracle_error_near_m,
    oracle_score,
    perfectly_corrected,
    score,
    worst_moment_s,
)
from pma_sim.registry import FAMILY_NAMES, family_argument, rate_dependent, table1_fit_errors_m

# The criteria against the paper's switch, from the third reversal on.
RMSE_OF_SWITCH = 0.9
MAX_OF_SWITCH = 0.7
DRIFT_START_S = 60.0
DRIFT_DURATION_S = 300.0
RECOVERED_WINDOW_S = (DRIFT_START_S + 120.0, DRIFT_DURATION_S)
# Issue 47's targets on a declared set (--set): the share of runs meeting both switch
# criteria and the mean minor-loop RMSE (% of stroke). Reported, never tuned on.
SET_SHARE_MEETING = 0.9
SET_MEAN_RMSE_PCT = 1.5


def table(form: str, seeds: list[int], duration_s: float, families, *,
          rate_hz: float = DEFAULT_RATE_HZ) -> list[str]:
    lines = [f'\n### {form} branches (RMSE | max error, cm (% of stroke), from the third '
             f'reversal on; mean RMSE and worst max over seeds {seeds})', '',
             '| family | rule | adaptation | ' + ' | '.join(
                 f'{kind} RMSE | {kind} max' for kind in PATH_KINDS) + ' |',
             '|---|---|---|' + '---|---|' * len(PATH_KINDS)]
    for family in families:
        for config in ALL_CONFIGS:
            for adapt in (False, True):
                variant = Config(config.memory, config.learn, adapt)
                cells = []
                for kind in PATH_KINDS:
                    results = [score(Scenario(family, kind, seed, duration_s, rate_hz=rate_hz),
                                     variant, form) for seed in seeds]
                    rmse = sum(r.rmse_m for r in results) / len(results)
                    worst = max(r.max_m for r in results)
                    cells.append(f'{rmse * 100:.3f} ({100 * rmse / STROKE_M:.2f}) | '
                                 f'{worst * 100:.3f} ({100 * worst / STROKE_M:.2f})')
                lines.append(f'| {family} | {config.label} | {"on" if adapt else "off"} | '
                             + ' | '.join(cells) + ' |')
    return lines


def criteria(form: str, seeds: list[int], duration_s: float, families, *,
             rate_hz: float = DEFAULT_RATE_HZ,
             candidate: Config = MIXED) -> tuple[list[str], bool]:
    lines = [f'\n### criteria, {form} branches ({candidate.label}, learning on)', '',
             '| scenario | RMSE / switch | max / switch | RMSE / best fixed rule (which) | '
             'adaptation on / off | RMSE % of stroke | oracle max / switch |',
             '|---|---|---|---|---|---|---|']
    passed = True
    for family in families:
        for kind in PATH_KINDS:
            for seed in seeds:
                scenario = Scenario(family, kind, seed, duration_s, rate_hz=rate_hz)
                ours = score(scenario, candidate, form)
                paper = score(scenario, PAPER, form)
                fixed = {config.label: score(scenario, config, form)
                         for config in (*STATIC_RULES, *LEARNED_RULES, PAPER)}
                best_label = min(fixed, key=lambda label: fixed[label].rmse_m)
                adapted = score(scenario, Config(candidate.memory, True, True), form)
                ratios = (ours.rmse_m / paper.rmse_m, ours.max_m / paper.max_m,
                          ours.rmse_m / fixed[best_label].rmse_m, adapted.rmse_m / ours.rmse_m)
                ok = (ratios[0] <= RMSE_OF_SWITCH, ratios[1] <= MAX_OF_SWITCH, ratios[2] <= 1.1,
                      ratios[3] <= 1.05, ours.rmse_pct <= 1.5)
                passed &= all(ok[:4])
                marks = ['' if good else ' **x**' for good in ok]
                oracle = '-' if rate_dependent(family) else \
                    f'{oracle_score(scenario).max_m / paper.max_m:.2f}'
                lines.append(
                    f'| {scenario.label} | {ratios[0]:.2f}{marks[0]} | {ratios[1]:.2f}{marks[1]}'
                    f' | {ratios[2]:.2f} ({best_label}){marks[2]} | {ratios[3]:.3f}{marks[3]} | '
                    f'{ours.rmse_pct:.2f}{marks[4]} | {oracle} |')
    return lines, passed


def _against_switch_run(form: str, scenario: Scenario
                        ) -> tuple[float, float, float, float | None, float, float]:
    ours, paper = score(scenario, MIXED, form), score(scenario, PAPER, form)
    at_s = worst_moment_s(scenario, MIXED, form)
    oracle = (None if rate_dependent(scenario.family)
              else oracle_error_near_m(scenario, at_s) / paper.max_m)
    return (ours.rmse_m / paper.rmse_m, ours.max_m / paper.max_m, at_s, oracle,
            ours.rmse_pct, ours.max_pct)


def against_switch(form: str, seeds: list[int], duration_s: float, families, *,
                   rate_hz: float, jobs: int, noise_free_pressure: bool = False,
                   kinds=PATH_KINDS, set_name: str | None = None) -> tuple[list[str], bool]:
    """The two criteria against the paper's switch on many seeds, in parallel; for a declared
    set (pma_sim.splits) also issue 47's targets on it. Met: every run meets both, or on a
    set, the set's targets."""
    scenarios = [Scenario(family, kind, seed, duration_s, rate_hz=rate_hz,
                          noise_free_pressure=noise_free_pressure)
                 for family in families for kind in kinds for seed in seeds]
    with ProcessPoolExecutor(jobs) as pool:
        results = list(pool.map(_against_switch_run, [form] * len(scenarios), scenarios))
    of_set = '' if set_name is None else f'{set_name} set, '
    lines = [f'\n### against the switch, {of_set}{form} branches ({MIXED.label}, learning on; '
             f'seeds {seeds}, {rate_hz:g} Hz)', '',
             '| scenario | RMSE / switch | max / switch | RMSE % of stroke | max % of stroke | '
             'max at [s] | oracle there / switch |', '|---|---|---|---|---|---|---|']
    misses, bound = [], 0
    for scenario, (rmse, worst, at_s, oracle, rmse_pct, max_pct) in zip(scenarios, results,
                                                                         strict=True):
        ok = (rmse <= RMSE_OF_SWITCH, worst <= MAX_OF_SWITCH)
        if not all(ok):
            misses.append(f'{scenario.label} {rmse:.2f}x / {worst:.2f}x at {at_s:.1f} s')
            bound += oracle is not None and oracle > MAX_OF_SWITCH
        lines.append(f'| {scenario.label} | {rmse:.2f}{"" if ok[0] else " **x**"} | '
                     f'{worst:.2f}{"" if ok[1] else " **x**"} | {rmse_pct:.2f} | '
                     f'{max_pct:.2f} | {at_s:.1f} | '
                     f'{"-" if oracle is None else f"{oracle:.2f}"} |')
    met = len(scenarios) - len(misses)
    mean_rmse_pct = float(np.mean([result[4] for result in results]))
    summary = (f'{met} of {len(scenarios)} runs meet both ({100 * met / len(scenarios):.0f} %); '
               f'{len(misses)} miss')
    if misses:
        summary += (f' ({", ".join(misses)}), {bound} of them where the oracle errs over '
                    f'{MAX_OF_SWITCH:g}x the switch\'s max within a sample of the same moment')
    summary += (f'. Minor-loop RMSE {mean_rmse_pct:.2f} % of stroke on average (runs '
                f'{min(r[4] for r in results):.2f}-{max(r[4] for r in results):.2f} %), max '
                f'{min(r[5] for r in results):.2f}-{max(r[5] for r in results):.2f} %')
    if set_name is not None:
        share_ok = met >= SET_SHARE_MEETING * len(scenarios)
        rmse_ok = mean_rmse_pct <= SET_MEAN_RMSE_PCT
        summary += (f'\n{set_name} set, issue 47 targets: at least '
                    f'{100 * SET_SHARE_MEETING:.0f} % of runs meet both switch criteria '
                    f'{"met" if share_ok else "NOT met"}; mean minor-loop RMSE at most '
                    f'{SET_MEAN_RMSE_PCT:g} % of stroke {"met" if rmse_ok else "NOT met"}')
    lines.append('\n' + summary)
    # On a declared set the targets are the set's (a share of the runs); else every run.
    return lines, (share_ok and rmse_ok) if set_name is not None else not misses


def drift(form: str, seed: int, families, *,
          rate_hz: float = DEFAULT_RATE_HZ) -> tuple[list[str], bool]:
    lines = [f'\n### drift, {form} branches ({MIXED.label}; drift +1.5 mm rest length, '
             f'x1.08 stroke from {DRIFT_START_S:.0f} s, time constant 30 s; random path, '
             f'seed {seed}; RMSE % of stroke per minute)', '',
             '| family | muscle | adaptation | ' + ' | '.join(
                 f'{start:.0f}-{start + 60:.0f} s' for start in range(0, int(DRIFT_DURATION_S),
                                                                     60)) + ' | recovered |',
             '|---|---|---|' + '---|' * (int(DRIFT_DURATION_S) // 60) + '---|']
    passed = True
    for family in families:
        clean = Scenario(family, 'random', seed, DRIFT_DURATION_S, rate_hz=rate_hz)
        drifting = Scenario(family, 'random', seed, DRIFT_DURATION_S, DRIFT_START_S,
                            rate_hz=rate_hz)
        unadapted = Config(MIXED.memory, True, False)
        drift_free = score(clean, unadapted, form, RECOVERED_WINDOW_S)
        floor = perfectly_corrected(drifting, unadapted, form, RECOVERED_WINDOW_S)
        for scenario, name in ((clean, 'no drift'), (drifting, 'drifting')):
            for adapt in (False, True):
                config = Config(MIXED.memory, True, adapt)
                windows = [score(scenario, config, form, (start, start + 60.0))
                           for start in range(0, int(DRIFT_DURATION_S), 60)]
                recovered = ''
                if scenario is drifting and adapt:
                    late = score(scenario, config, form, RECOVERED_WINDOW_S)
                    ratio = late.rmse_m / floor.rmse_m
                    passed &= ratio <= 1.1
                    recovered = (f'{ratio:.2f}x a perfect correction\'s error'
                                 + ('' if ratio <= 1.1 else ' **x**')
                                 + f' ({late.rmse_m / drift_free.rmse_m:.2f}x the drift-free)')
                lines.append(f'| {family} | {name} | {"on" if adapt else "off"} | '
                             + ' | '.join(f'{w.rmse_pct:.2f}' for w in windows)
                             + f' | {recovered} |')
    return lines, passed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+',
                        help='path seeds (default: 1 2; with --set, the set\'s: 1-8)')
    parser.add_argument('--forms', nargs='+', default=['sigmoid', 'hill'])
    parser.add_argument('--duration', type=float, default=180.0, help='path length [s]')
    parser.add_argument('--rate-hz', type=float, nargs='+', default=[DEFAULT_RATE_HZ],
                        help=f'samples per second, one run per rate (default '
                             f'{DEFAULT_RATE_HZ:g}, the firmware\'s maximum; driver_node asks '
                             'for 20 by default)')
    parser.add_argument('--set', choices=(*splits.SETS, 'both'), dest='muscle_set',
                        help='the families and seeds of a set declared in pma_sim.splits '
                             '(tuning: the defaults may be chosen on it; validation: run only '
                             'to report), or each set apart (both); with --against-switch, '
                             'also issue 47\'s targets on the set (at least 90 %% of runs '
                             'meeting both switch criteria, mean RMSE at most 1.5 %% of stroke)')
    parser.add_argument('--families', nargs='+', type=family_argument,
                        help='default: the simulator\'s four families and bouc-wen; '
                             'duhem:RISING:FALLING (kPa) adds a Duhem muscle with other '
                             'approach scales, fitted to Table 1 (asymmetric is duhem:15:100); '
                             'gpi[:BULGE] a generalized Prandtl-Ishlinskii muscle, asymmetric '
                             'with return-point memory (pma_sim.generalized_play); '
                             'friction[:WIDEST] braid friction growing with the pressure, a '
                             'late sharp onset (pma_sim.friction); '
                             'creep:INNER:SHARE:TAU narrow, wide or asymmetric with a share of '
                             'every length change lagged by TAU seconds (creep is '
                             'creep:narrow:0.25:0.6)')
    parser.add_argument('--against-switch', action='store_true',
                        help='only the two criteria against the switch, with the oracle at '
                             'the moment of the largest error (fast: for many seeds)')
    parser.add_argument('--noise-free-pressure', action='store_true',
                        help='with --against-switch: the mix and the switch read the true '
                             'pressure instead of the sensor\'s (how much of their errors '
                             'the pressure reading\'s noise makes)')
    parser.add_argument('--kinds', nargs='+', choices=ALL_PATH_KINDS, default=list(PATH_KINDS),
                        help='with --against-switch: the paths (default: the tables\' '
                             'nested and random ramps; sines and damped are smooth)')
    parser.add_argument('--jobs', type=int, default=os.cpu_count() or 1,
                        help='processes for --against-switch (default: one per core)')
    args = parser.parse_args()
    if args.noise_free_pressure and not args.against_switch:
        parser.error('--noise-free-pressure needs --against-switch')
    if args.kinds != list(PATH_KINDS) and not args.against_switch:
        parser.error('--kinds needs --against-switch')
    if args.muscle_set is not None and args.families is not None:
        parser.error('--set chooses the families: give --set or --families, not both')
    if args.muscle_set is None:
        groups = [(None, args.families or list(SCORED_FAMILIES), args.seeds or [1, 2])]
    else:
        chosen = splits.SETS.values() if args.muscle_set == 'both' \
            else [splits.SETS[args.muscle_set]]
        groups = [(muscle_set.name, list(muscle_set.families),
                   args.seeds or list(muscle_set.seeds)) for muscle_set in chosen]
    start = time.monotonic()
    verdicts, all_met = [], True
    for rate_hz in args.rate_hz:
        for set_name, families, seeds in groups:
            lines, met = _run(args, set_name, families, seeds, rate_hz)
            verdicts += lines
            all_met &= met
    print('\n' + '\n'.join(verdicts))
    print(f'({time.monotonic() - start:.0f} s)')
    # A miss of the default model's criteria fails `make bench` (identify alone, the default
    # before the mix, is reported only).
    return 0 if all_met else 1


def _run(args, set_name: str | None, families: list[str], seeds: list[int],
         rate_hz: float) -> tuple[list[str], bool]:
    """Every branch form on these families, seeds and rate; the verdict lines, and whether
    the default model met its criteria (drift recovery included) on all of them."""
    of_set = '' if set_name is None else f' of the {set_name} set'
    print(f'\n# Minor loops on the muscle families{of_set} (paths of {args.duration:.0f} s at '
          f'{rate_hz:g} Hz, stroke {STROKE_M * 100:.2f} cm)')
    for family in families:
        errors = table1_fit_errors_m(family)
        if errors is not None:
            print(f'{family}: Table 1 fit RMSE {100 * np.sqrt(np.mean(errors ** 2)):.3f} cm, '
                  f'max {100 * np.max(np.abs(errors)):.3f} cm over {errors.size} points')
    verdicts, all_met = [], True
    where = f'{"" if set_name is None else set_name + " set, "}{rate_hz:g} Hz, '
    for form in args.forms:
        if args.against_switch:
            lines, passed = against_switch(form, seeds, args.duration, families,
                                           rate_hz=rate_hz, jobs=args.jobs,
                                           noise_free_pressure=args.noise_free_pressure,
                                           kinds=args.kinds, set_name=set_name)
            print('\n'.join(lines), flush=True)
            verdicts.append(f'{where}{form}: criteria against the switch '
                            f'{"met" if passed else "NOT met"}')
            all_met &= passed
            continue
        print('\n'.join(table(form, seeds, args.duration, families, rate_hz=rate_hz)),
              flush=True)
        lines, passed = criteria(form, seeds, args.duration, families, rate_hz=rate_hz)
        print('\n'.join(lines), flush=True)
        alone_lines, alone_passed = criteria(form, seeds, args.duration, families,
                                             rate_hz=rate_hz, candidate=IDENTIFY)
        print('\n'.join(alone_lines), flush=True)
        drifting = [family for family in families if family in FAMILY_NAMES]
        if drifting:
            drift_lines, drift_passed = drift(form, seeds[0], drifting, rate_hz=rate_hz)
            print('\n'.join(drift_lines), flush=True)
            drift_verdict = f'drift recovery {"met" if drift_passed else "NOT met"}'
            all_met &= drift_passed
        else:   # no family with a drift option among them: nothing was checked
            drift_verdict = 'drift recovery not checked (no family with a drift option)'
        verdicts.append(f'{where}{form}: minor-loop criteria {"met" if passed else "NOT met"} '
                        f'(identify alone: {"met" if alone_passed else "NOT met"}), '
                        + drift_verdict)
        all_met &= passed
    return verdicts, all_met


if __name__ == '__main__':
    sys.exit(main())

"""Fit the muscle families to the paper's Table 1 and write `family_fits.py`.

`python -m pma_sim.fit_families [--write]` (scipy; about a minute on one core).
Without --write it prints the fits and the file it would write. The narrow family's fit
is `muscle.fit_major_loop` (its constants stay in muscle.py, `python -m
pma_sim.muscle` repeats that one); `creep` is the narrow muscle with a creep element
whose two constants are a design choice (its holds settle on the narrow loop).

- wide: variable projection. For a warp (dead zone, K, n) the weights of 20 plays with
  half-widths 0..0.45 (in the warped input) are a non-negative least-squares problem with a
  second-difference smoothness penalty (SMOOTHING), so the weight profile is smooth, not
  a few spikes; the warp is fitted around it (multi-start TRF).
- asymmetric: the two envelopes (a shared rest length, 6 numbers each) are fitted so that
  the simulated steady loop, with the approach scales fixed at RISING_SCALE_PA and
  FALLING_SCALE_PA, matches Table 1.
"""

from __future__ import annotations

import argparse
import itertools
import pprint
from dataclasses import asdict
from pathlib import Path

import numpy as np

from pma_sim import families
from pma_sim.muscle import (
    TABLE1_FIT,
    TABLE1_LENGTH_DECREASING_M,
    TABLE1_LENGTH_INCREASING_M,
    TABLE1_PRESSURE_PA,
    major_loop_m,
)

PLAYS = 20
MAX_RADIUS = 0.45          # a play this wide needs 0.9 of the warped range to move
SMOOTHING = 0.03           # weight of the second-difference penalty on the play weights
RISING_SCALE_PA = 15_000.0   # asymmetric: inflating, the length catches the envelope fast
FALLING_SCALE_PA = 100_000.0  # deflating, slowly
CREEP = {'share': 0.25, 'time_constant_s': 0.6}
TARGET = np.concatenate([TABLE1_LENGTH_INCREASING_M, TABLE1_LENGTH_DECREASING_M])
OUTPUT = Path(__file__).with_name('family_fits.py')


def classic_plays(rest_length_m: float, warp, radii, weights_m) -> families.PlayParams:
    """The `wide` family's parameters from fit_plays' pieces."""
    return families.PlayParams(rest_length_m, float(warp[0]), float(warp[1]), float(warp[2]),
                               tuple(float(r) for r in radii),
                               tuple(float(w) for w in weights_m))


def _play_design(params_for, warp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    radii = np.linspace(0.0, MAX_RADIUS, PLAYS)
    columns = []
    for j in range(PLAYS):
        unit = params_for(0.0, warp, radii, np.eye(PLAYS)[j])
        up, down = families.play_major_loop_m(unit, TABLE1_PRESSURE_PA)
        columns.append(-np.concatenate([up, down]))   # length lost per unit weight
    return np.array(columns).T, radii


def fit_wide(starts: int = 8, seed: int = 0) -> families.PlayParams:
    return fit_plays(classic_plays, starts, seed)


def fit_plays(params_for, starts: int, seed: int, target: np.ndarray = TARGET):
    """Warp and play weights fitted to Table 1 by variable projection; `params_for(rest, warp,
    radii, weights)` makes the parameters (PlayParams or a generalized play's). `target`: what
    the plays' loop must make (Table 1, less what a muscle adds to its plays: ratchet.py)."""
    from scipy.optimize import least_squares, nnls

    rest = float(TABLE1_LENGTH_INCREASING_M[0])
    penalty = np.sqrt(SMOOTHING) * np.diff(np.eye(PLAYS), 2, axis=0)
    scale = np.array([1e5, 1e5, 1.0])

    def weights_for(warp):
        design, _ = _play_design(params_for, warp)
        weights, _ = nnls(np.vstack([design, penalty]),
                          np.concatenate([rest - target, np.zeros(PLAYS - 2)]))
        return weights, rest - design @ weights - target

    rng = np.random.default_rng(seed)
    best = None
    for k in range(starts):
        x0 = np.array([0.5, 1.5, 1.5]) if k == 0 else rng.uniform([0.0, 0.5, 0.8],
                                                                 [0.8, 3.0, 4.0])
        result = least_squares(lambda z: weights_for(z * scale)[1], x0,
                               bounds=([0.0, 0.2, 0.5], [1.0, 6.0, 6.0]))
        if best is None or result.cost < best.cost:
            best = result
    warp = best.x * scale
    weights, _ = weights_for(warp)
    _, radii = _play_design(params_for, warp)
    return params_for(rest, warp, radii, weights)


_ENVELOPE_LOWER = [0.03, 0.0, 0.0, 30e3, 0.0, 30e3]   # no step sharper than 30 kPa
_ENVELOPE_UPPER = [0.1, 1.0, 600e3, 400e3, 700e3, 400e3]
_ENVELOPE_SCALE = np.array([0.01, 1.0, 1e5, 1e5, 1e5, 1e5])


def _duhem(z: np.ndarray, rising_scale_pa: float,
           falling_scale_pa: float) -> families.DuhemParams:
    rest, rising, falling = z[0] * 0.1, z[1:7] * _ENVELOPE_SCALE, z[7:13] * _ENVELOPE_SCALE
    return families.DuhemParams(rest, families.EnvelopeParams(*rising),
                                families.EnvelopeParams(*falling), rising_scale_pa,
                                falling_scale_pa)


def fit_asymmetric(starts: int = 4, seed: int = 0, rising_scale_pa: float = RISING_SCALE_PA,
                   falling_scale_pa: float = FALLING_SCALE_PA) -> families.DuhemParams:
    """The Duhem muscle whose steady loop fits Table 1, for the given approach scales.

    Other scales than the `asymmetric` family's give other Duhem muscles on the same major
    loop: variants for judging the model (pma_sim.registry: duhem, gpi, friction).
    """
    from scipy.optimize import least_squares

    def model(z):
        return _duhem(z, rising_scale_pa, falling_scale_pa)

    def residuals(z):
        return duhem_loop_errors_m(model(z))

    lower = np.concatenate([[2.9], np.tile(np.array(_ENVELOPE_LOWER) / _ENVELOPE_SCALE, 2)])
    upper = np.concatenate([[3.1], np.tile(np.array(_ENVELOPE_UPPER) / _ENVELOPE_SCALE, 2)])
    envelope = np.array([0.062, 0.25, 150e3, 65e3, 390e3, 60e3]) / _ENVELOPE_SCALE
    rng = np.random.default_rng(seed)
    best = None
    for k in range(starts):
        x0 = np.concatenate([[3.006], envelope, envelope])
        if k:
            x0 = np.clip(x0 * rng.uniform(0.7, 1.3, x0.size), lower, upper)
            x0[0] = 3.006
        result = least_squares(residuals, x0, bounds=(lower, upper), x_scale='jac')
        if best is None or result.cost < best.cost:
            best = result
    return model(best.x)


def duhem_loop_errors_m(params: families.DuhemParams) -> np.ndarray:
    """A Duhem muscle's steady loop minus Table 1 (22 values)."""
    return np.concatenate(families.duhem_major_loop_m(params, TABLE1_PRESSURE_PA)) - TARGET


def creep_steady_loop_m(hold_s: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """The creep family's loop as the paper measured it: the end of a 10 s hold per level."""
    from pma_sim.registry import muscle_family  # the registry builds on this module

    muscle = muscle_family('creep')
    t = 0.0
    lengths = []
    levels = np.concatenate([TABLE1_PRESSURE_PA, TABLE1_PRESSURE_PA[::-1]])
    for cycle, level in itertools.product(range(2), levels):
        t += 1.0                      # a 1 s ramp to the level, then the hold
        muscle.update(level, t)
        t += hold_s
        length = muscle.update(level, t)
        if cycle == 1:
            lengths.append(length)
    n = TABLE1_PRESSURE_PA.size
    return np.array(lengths[:n]), np.array(lengths[n:][::-1])


def loop_errors_m(name: str) -> np.ndarray:
    """Model loop minus Table 1 (22 values) for a family as it is shipped."""
    if name == 'narrow':
        up, down = major_loop_m(TABLE1_FIT, TABLE1_PRESSURE_PA)
    elif name == 'wide':
        up, down = families.play_major_loop_m(families.wide_params(), TABLE1_PRESSURE_PA)
    elif name == 'asymmetric':
        return duhem_loop_errors_m(families.asymmetric_params())
    else:
        up, down = creep_steady_loop_m()
    return np.concatenate([up, down]) - TARGET


def _summary(errors: np.ndarray) -> str:
    return (f'RMSE {np.sqrt(np.mean(errors ** 2)) * 100:.3f} cm, '
            f'max {np.abs(errors).max() * 100:.3f} cm over {errors.size} points')


def _plain(value):
    """Floats rounded to 7 significant digits, tuples as lists: readable, exact enough."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return float(f'{float(value):.7g}')


def render(wide: families.PlayParams, asymmetric: families.DuhemParams,
           fits: dict[str, str]) -> str:
    wide_dict = _plain(asdict(wide))
    lines = [
        '"""Fitted constants of the muscle families (families.py); data, not code.',
        '',
        'Written by `python -m pma_sim.fit_families --write` (docs/simulated-rig.md);',
        'do not edit by hand. Fit of each family\'s steady major loop to Table 1:',
        '',
        *(f'- {name}: {text}' for name, text in fits.items()),
        '"""',
        '',
        f'WIDE = {pprint.pformat(wide_dict, width=90, compact=True, sort_dicts=False)}',
        '',
        f'ASYMMETRIC = {pprint.pformat(_plain(asdict(asymmetric)), width=90, sort_dicts=False)}',
        '',
        f'CREEP = {CREEP!r}',
        '',
    ]
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description='Fit the muscle families to Table 1.')
    parser.add_argument('--write', action='store_true', help=f'write {OUTPUT.name}')
    args = parser.parse_args(argv)
    wide = fit_wide()
    asymmetric = fit_asymmetric()
    fits = {}
    for name, errors in (
            ('narrow', loop_errors_m('narrow')),
            ('wide', np.concatenate(families.play_major_loop_m(wide, TABLE1_PRESSURE_PA))
             - TARGET),
            ('asymmetric', duhem_loop_errors_m(asymmetric))):
        fits[name] = _summary(errors)
    fits['creep'] = ('the narrow fit at the end of each hold (creep share '
                     f"{CREEP['share']}, time constant {CREEP['time_constant_s']} s)")
    text = render(wide, asymmetric, fits)
    print(text)
    if args.write:
        OUTPUT.write_text(text)
        print(f'wrote {OUTPUT}')


if __name__ == '__main__':
    main()

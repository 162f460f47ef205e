"""The model's scalar formulas, compiled (numba).

Each formula has its one home here: a branch form's length and closed-form inverse, the knot
interpolation of the learned correction, a scanning curve's length, where a reversal lies
across the loop and its play share, the local offset's fade. The classes (branches.py,
correction.py, curves.py, local_offset.py, memory.py) call them for one value.

This module imports nothing of pma_model: numba freezes a global's value into a cached
kernel and only notices a change of this file, so every number that belongs to another
module (the knots, the constants) comes in as an argument, never as a global.

A branch row (`Branch.kernel_row`): [formula, four parameters, knot count K, K knot
pressures, K base lengths at the knots, K offsets]; K = 0 for a branch without a learned
correction (the three blocks absent).
"""

from __future__ import annotations

import math

import numba


def _probe():
    return 0.0


def _can_cache() -> bool:
    """Whether numba finds a writable directory for this module's cache (beside the source,
    NUMBA_CACHE_DIR or the user's cache directory); its decorator raises where it finds none."""
    try:
        numba.njit(cache=True)(_probe)
    except RuntimeError:   # "cannot cache function ...: no locator available"
        return False
    return True


# False: every process compiles what it calls (seconds, not wrong).
CACHING = _can_cache()


def compiled(**options):
    """numba.njit, with the on-disk cache where there is one."""
    return numba.njit(cache=CACHING, **options)


# The branch formulas the kernel has (a Branch class's `kernel_formula`).
SIGMOID, HILL = 0.0, 1.0
# A branch row's layout.
ROW_FORMULA, ROW_PARAMETERS, ROW_KNOTS = 0, 1, 5
ROW_HEAD = 6        # the knot blocks start here
# How a memory rule's path goes on from a state (a rule class's `path_kind`): along the
# turning-point stack's scanning curves, or the friction band's hold, then the major branch.
PATH_STACK, PATH_BAND = 0, 1


# --- Python's min and max (NaN passes as they pass it) -----------------------------------

@compiled()
def py_min(a, b):
    """min(a, b) as Python computes it: a unless b < a."""
    return b if b < a else a


@compiled()
def py_max(a, b):
    """max(a, b) as Python computes it: a unless b > a."""
    return b if b > a else a


# --- branch forms --------------------------------------------------------------------------

@compiled()
def sigmoid_length(l0, a, b, c, p):
    """The paper's branch L = L0 - a*L0 / (1 + exp(-b*P))**c; P below 0 counts as 0."""
    # (1 + exp(-bP))**-c written as exp(-c*log(1 + exp(-bP))) so no power overflows.
    saturation = math.exp(-c * math.log1p(math.exp(-b * py_max(p, 0.0))))
    return l0 - a * l0 * saturation


@compiled(error_model='numpy')
def sigmoid_pressure(l0, a, b, c, length):
    """The sigmoid's closed-form inverse, no range check: NaN where it has no real answer."""
    # u = log(1 + exp(-bP)); expm1 keeps precision near saturation, where u -> 0.
    u = math.log(a * l0 / (l0 - length)) / c
    result = -math.log(math.expm1(u)) / b
    return result if math.isfinite(result) else math.nan


@compiled(error_model='numpy')
def hill_length(l0, dl, k, n, p):
    """A Hill curve L = L0 - dL * P**n / (P**n + K**n); P below 0 counts as 0."""
    powered = (py_max(p, 0.0) / k) ** n
    fraction = 1.0 if powered == math.inf else powered / (1.0 + powered)
    return l0 - dl * fraction


@compiled(error_model='numpy')
def hill_pressure(l0, dl, k, n, length):
    """The Hill curve's closed-form inverse, no range check: NaN where it has no real
    answer (a negative fraction, or one at or beyond saturation)."""
    fraction = (l0 - length) / dl
    result = k * (fraction / (1.0 - fraction)) ** (1.0 / n)
    return result if math.isfinite(result) and fraction >= 0.0 else math.nan


@compiled()
def base_length(row, p):
    """The length of a row's branch form (its correction left out) at one pressure."""
    a, b, c, d = row[1], row[2], row[3], row[4]
    if row[ROW_FORMULA] == SIGMOID:
        return sigmoid_length(a, b, c, d, p)
    return hill_length(a, b, c, d, p)


@compiled()
def base_pressure(row, length):
    """The closed-form inverse of a row's branch form (its correction left out)."""
    a, b, c, d = row[1], row[2], row[3], row[4]
    if row[ROW_FORMULA] == SIGMOID:
        return sigmoid_pressure(a, b, c, d, length)
    return hill_pressure(a, b, c, d, length)


# --- the learned correction (correction.py) -----------------------------------------------

@compiled()
def knot_share(row, p, base):
    """(k, share): the correction at p is d_k + (d_{k+1} - d_k) * share, interpolated along
    the base branch's own length (`base`, its length at p); share is 0 beyond the knots and
    on an interval where the base does not fall."""
    knots = int(row[ROW_KNOTS])
    first, at = ROW_HEAD, ROW_HEAD + knots
    if p <= row[first]:
        return 0, 0.0
    if p >= row[first + knots - 1]:
        return knots - 1, 0.0
    k = 0
    while row[first + k + 1] <= p:   # bisect_right - 1: the last knot at or below p
        k += 1
    drop = row[at + k] - row[at + k + 1]
    return k, ((row[at + k] - base) / drop if drop > 0.0 else 0.0)


@compiled()
def interpolated(row, k, share):
    """The correction d_k + (d_{k+1} - d_k) * share (`knot_share`'s k and share)."""
    offsets = ROW_HEAD + 2 * int(row[ROW_KNOTS])
    if share == 0.0:
        return row[offsets + k]
    return row[offsets + k] + (row[offsets + k + 1] - row[offsets + k]) * share


@compiled()
def branch_length(row, p):
    """A branch's length at one pressure, its learned correction added."""
    base = base_length(row, p)
    if row[ROW_KNOTS] == 0.0:
        return base
    k, share = knot_share(row, p, base)
    return base + interpolated(row, k, share)


@compiled()
def branch_pressure(row, length):
    """A branch's closed-form inverse, its learned correction undone, no range check: NaN
    where it has none. On knot interval k the corrected length is B(P) + d_k + r (B_k - B(P)),
    r = (d_{k+1} - d_k) / (B_k - B_{k+1}), so B(P) = (L - d_k - r B_k) / (1 - r); a flat
    interval (r >= 1) answers its lowest pressure."""
    if not math.isfinite(length):
        return math.nan
    knots = int(row[ROW_KNOTS])
    if knots == 0:
        return base_pressure(row, length)
    first, at, off = ROW_HEAD, ROW_HEAD + knots, ROW_HEAD + 2 * knots
    if length > row[at] + row[off]:
        return math.nan    # longer than at 0 Pa (flat below: the least pressure is 0)
    if length <= row[at + knots - 1] + row[off + knots - 1]:
        return base_pressure(row, length - row[off + knots - 1])
    i = 0
    while row[at + i] + row[off + i] > length:
        i += 1
    if row[at + i] + row[off + i] == length:
        return row[first + i]   # the least pressure of a flat stretch too
    k = i - 1
    drop = row[at + k] - row[at + k + 1]
    ratio = (row[off + k + 1] - row[off + k]) / drop if drop > 0.0 else 1.0
    if ratio >= 1.0:
        return row[first + k]
    return base_pressure(row, (length - row[off + k] - ratio * row[at + k]) / (1.0 - ratio))


# --- scanning curves (curves.py) and the local offset (local_offset.py) -------------------

@compiled()
def curve_knee(l_origin, l_target, b_origin, b_target, flat_span_m):
    """(flat, knee) of a curve through O and T: flat when the major branch barely moves
    between their pressures; the knee q where the play-like shape stops holding."""
    flat = abs(b_origin - b_target) < flat_span_m
    ratio = 1.0 if flat else (l_origin - l_target) / (b_origin - b_target)
    return flat, (ratio if 0.0 < ratio < 1.0 else 1.0)


@compiled()
def curve_length(shape, l_origin, l_target, b_origin, b_target, flat, share, knee):
    """A scanning curve's length where its major branch is `shape` long: L_T + (L_O - L_T) *
    (w min(1, s / q) + (1 - w) s), s = (B - B_T) / (B_O - B_T) clipped to 0..1 (Madelung's,
    w = 0, not clipped); a flat curve is the branch shifted through O."""
    if flat:
        return l_origin + (shape - b_origin)
    if share == 0.0:
        return l_target + (l_origin - l_target) * (shape - b_target) / (b_origin - b_target)
    s = py_min(py_max((shape - b_target) / (b_origin - b_target), 0.0), 1.0)
    held = py_min(1.0, s / knee)
    return l_target + (l_origin - l_target) * (share * held + (1.0 - share) * s)


@compiled()
def origin_depth(toward_m, other_m, l_origin, narrow_loop_m):
    """Where a reversal at length l_origin lies across the loop: 0 on the branch its curve
    heads for (`toward_m` there), 1 on the other; 1 where the branches are narrower than
    narrow_loop_m."""
    width = other_m - toward_m
    if abs(width) < narrow_loop_m:
        return 1.0
    return py_min(1.0, py_max(0.0, (l_origin - toward_m) / width))


@compiled()
def play_share(share, slope, depth, mid_depth):
    """The 'identify' share of a curve whose reversal lies at `depth`, within 0..1."""
    return py_min(1.0, py_max(0.0, share + slope * (depth - mid_depth)))


@compiled()
def faded_offset(offset_m, play_at_pa, p, half_play_pa, fade_pa):
    """The local offset once pressure has gone straight from its play's position to p."""
    if math.isnan(play_at_pa) or offset_m == 0.0:
        return offset_m
    travel = py_max(abs(p - play_at_pa) - half_play_pa, 0.0)
    return offset_m * math.exp(-travel / fade_pa)

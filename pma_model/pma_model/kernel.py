"""The model's scalar formulas, compiled (numba), and the mix's inverse along the path in one call.

Each formula has its one home here: a branch form's length and closed-form inverse, the knot
interpolation of the learned correction, a scanning curve's length, where a reversal lies
across the loop and its play share, the local offset's fade, the path pressure would follow
from a state (the turning-point stack's curves, or the friction band's hold), the mixed length
along it and a root find (scipy's brentq.c, step for step). The classes (branches.py,
correction.py, curves.py, local_offset.py) call them for one value; mix.RuleMix's inverse
calls `mixed_path_pressure` once, with the state packed as arrays.

This module imports nothing of pma_model: numba freezes a global's value into a cached
kernel and only notices a change of this file, so every number that belongs to another
module (the knots, the constants) comes in as an argument, never as a global.

A branch row (`Branch.kernel_row`): [formula, four parameters, knot count K, K knot
pressures, K base lengths at the knots, K offsets]; K = 0 for a branch without a learned
correction (the three blocks absent). A branch table stacks rows, zero-padded.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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



@compiled()
def branch_lengths(row, pressures):
    """branch_length at each of `pressures` (1-D): the array form of the same formula."""
    result = np.empty(pressures.size)
    for i in range(pressures.size):
        result[i] = branch_length(row, pressures[i])
    return result


@compiled()
def branch_pressures(row, lengths):
    """branch_pressure at each of `lengths` (1-D): the array form of the same formula."""
    result = np.empty(lengths.size)
    for i in range(lengths.size):
        result[i] = branch_pressure(row, lengths[i])
    return result


# --- scanning curves (curves.py) and the local offset (local_offset.py) -------------------

@compiled()
def curve_knee(l_origin, l_target, b_origin, b_target, flat_span_m):
    """(flat, knee) of a curve through O and T: flat when the major branch barely moves
    between their pressures; the knee q where the play-like shape stops holding."""
    flat = abs(b_origin - b_target) < flat_span_m
    ratio = 1.0 if flat else (l_origin - l_target) / (b_origin - b_target)
    return flat, (ratio if 0.0 < ratio < 1.0 else 1.0)


@compiled()
def curve_coordinate(shape, b_target, b_origin, knee):
    """(s, min(1, s / q)): where the major branch's length `shape` lies between T and O,
    clipped to 0..1, and the play-like shape's coordinate there."""
    s = py_min(py_max((shape - b_target) / (b_origin - b_target), 0.0), 1.0)
    return s, py_min(1.0, s / knee)


@compiled()
def curve_length(shape, l_origin, l_target, b_origin, b_target, flat, share, knee):
    """A scanning curve's length where its major branch is `shape` long: L_T + (L_O - L_T) *
    (w min(1, s / q) + (1 - w) s), s = (B - B_T) / (B_O - B_T) clipped to 0..1 (Madelung's,
    w = 0, not clipped); a flat curve is the branch shifted through O."""
    if flat:
        return l_origin + (shape - b_origin)
    if share == 0.0:
        return l_target + (l_origin - l_target) * (shape - b_target) / (b_origin - b_target)
    s, held = curve_coordinate(shape, b_target, b_origin, knee)
    return l_target + (l_origin - l_target) * (share * held + (1.0 - share) * s)


@compiled()
def curve_shapes(shape, l_origin, l_target, b_origin, b_target, flat, knee):
    """(play-like, Madelung) lengths of a curve where its major branch is `shape` long: the
    two shapes a play share mixes (both clipped between T and O; a flat curve has one)."""
    if flat:
        value = l_origin + (shape - b_origin)
        return value, value
    s, held = curve_coordinate(shape, b_target, b_origin, knee)
    return l_target + (l_origin - l_target) * held, l_target + (l_origin - l_target) * s


@compiled()
def curve_lengths(shapes, l_origin, l_target, b_origin, b_target, flat, share, knee):
    """curve_length at each of `shapes` (1-D): the array form of the same formula."""
    result = np.empty(shapes.size)
    for i in range(shapes.size):
        result[i] = curve_length(shapes[i], l_origin, l_target, b_origin, b_target, flat,
                                 share, knee)
    return result


@compiled()
def drifted_length(reference_m, shift_m, gain, model_length_m):
    """A model length as drift moves it (adaptation.Drift): shifted, and scaled about the
    reference length; for a float or an array alike."""
    return reference_m + shift_m + gain * (model_length_m - reference_m)


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


# --- the mix's inverse along the path -------------------------------------------------------

# An expert's row (RuleMix packs it from OnlineModel.drift and HysteresisModel.path_state).
(E_WEIGHT, E_REFERENCE, E_SHIFT, E_GAIN, E_PRESSURE, E_LENGTH, E_RISING, E_PATH, E_SHARED,
 E_SHARE_UP, E_SHARE_DOWN, E_SLOPE_UP, E_SLOPE_DOWN, E_INCREASING, E_DECREASING, E_STACK,
 E_DEPTH, E_MAX) = range(18)
EXPERT_COLUMNS = 18
# The call's numbers: the state's, then the constants (from the modules that own them).
(S_HERE, S_MAX, S_SETTLED, S_OFFSET, S_PLAY_AT, S_HALF_PLAY, S_FADE, S_MID_DEPTH, S_NARROW,
 S_FLAT_SPAN, S_XTOL, S_RTOL, S_ROUNDING, S_MAXITER) = range(14)
SCALARS = 14
# A path segment: the expert's curve from p_from to p_to (major: a branch table row; origin
# 0: the major branch itself), through O and T, its play share and O's depth across the loop.
(G_FROM, G_TO, G_MAJOR, G_ORIGIN, G_L_ORIGIN, G_L_TARGET, G_B_ORIGIN, G_B_TARGET, G_FLAT,
 G_SHARE, G_KNEE, G_P_ORIGIN, G_P_TARGET, G_DEPTH) = range(14)
SEGMENT_COLUMNS = 14


@compiled()
def _curve_segment(out, j, branches, major, other, shared, share, slope, origin_p, origin_l,
                   target_p, target_l, scalars):
    """The scanning curve from reversal O toward T on branch row `major`, into out[j]
    (HysteresisModel._curve with its rule's curve)."""
    toward = branch_length(branches[major], origin_p)
    w = 0.0
    depth = scalars[S_MID_DEPTH]
    if shared:   # 'identify': its play share at O's depth across the loop
        depth = origin_depth(toward, branch_length(branches[other], origin_p), origin_l,
                             scalars[S_NARROW])
        w = play_share(share, slope, depth, scalars[S_MID_DEPTH])
    out[j, G_P_ORIGIN], out[j, G_P_TARGET], out[j, G_DEPTH] = origin_p, target_p, depth
    b_target = branch_length(branches[major], target_p)
    flat, knee = curve_knee(origin_l, target_l, toward, b_target, scalars[S_FLAT_SPAN])
    out[j, G_ORIGIN] = 1.0
    out[j, G_L_ORIGIN], out[j, G_L_TARGET] = origin_l, target_l
    out[j, G_B_ORIGIN], out[j, G_B_TARGET] = toward, b_target
    out[j, G_FLAT] = 1.0 if flat else 0.0
    out[j, G_SHARE], out[j, G_KNEE] = w, knee


@compiled()
def path_segments(expert, stacks, branches, rising, scalars, out, count):
    """The pieces of the path pressure would follow one way from an expert's state, into
    out[count:]; the new count. The stack rules' (PATH_STACK): the curve in force, then
    through wiping-out each older one, to 0 Pa or the maximum. The band's (PATH_BAND): the
    length holds until the major branch meets it, then follows that branch."""
    p_here, l_here = expert[E_PRESSURE], expert[E_LENGTH]
    major = int(expert[E_INCREASING] if rising else expert[E_DECREASING])
    other = int(expert[E_DECREASING] if rising else expert[E_INCREASING])
    limit = expert[E_MAX] if rising else 0.0
    if expert[E_PATH] == PATH_BAND:
        meets = branch_pressure(branches[major], l_here)
        if math.isnan(meets):
            meets = p_here
        out[count, G_MAJOR] = major
        out[count, G_FROM] = py_max(p_here, meets) if rising else py_min(p_here, meets)
        out[count, G_TO] = limit
        return count + 1
    shared = expert[E_SHARED] != 0.0
    share = expert[E_SHARE_UP] if rising else expert[E_SHARE_DOWN]
    slope = expert[E_SLOPE_UP] if rising else expert[E_SLOPE_DOWN]
    start, depth = int(expert[E_STACK]), int(expert[E_DEPTH])
    # The turning points the path meets, oldest first: the stack, and the current state
    # when going this way is a reversal.
    points = np.empty((depth + 1, 2))
    for k in range(depth):   # not a slice assignment: that costs seconds more to compile
        points[k, 0], points[k, 1] = stacks[start + k, 0], stacks[start + k, 1]
    if rising != (expert[E_RISING] != 0.0):
        points[depth, 0], points[depth, 1] = p_here, l_here
        depth += 1
    p_from = p_here
    while True:
        out[count, G_MAJOR] = major
        if depth >= 2:
            _curve_segment(out, count, branches, major, other, shared, share, slope,
                           points[depth - 1, 0], points[depth - 1, 1],
                           points[depth - 2, 0], points[depth - 2, 1], scalars)
        elif depth == 1:   # toward the anchor at the end of the major branch
            _curve_segment(out, count, branches, major, other, shared, share, slope,
                           points[0, 0], points[0, 1], limit,
                           branch_length(branches[major], limit), scalars)
        p_to = points[depth - 2, 0] if depth >= 2 else limit
        final = depth < 2 or ((p_to >= limit) if rising else (p_to <= limit))
        if final:
            p_to = limit
        out[count, G_FROM], out[count, G_TO] = p_from, p_to
        count += 1
        if final:
            return count
        depth -= 2
        p_from = p_to


@compiled()
def empty_segments(capacity):
    """A segment table to fill: every curve the major branch itself (no origin, knee 1)."""
    # np.empty and loops: np.zeros and slice assignments cost seconds more to compile.
    segments = np.empty((capacity, SEGMENT_COLUMNS))
    for j in range(capacity):
        for column in range(SEGMENT_COLUMNS):
            segments[j, column] = 0.0
        segments[j, G_KNEE] = 1.0
    return segments


@compiled()
def path_of(expert, stacks, branches, rising, scalars):
    """The segment table of one expert's path (`path_segments`), for the classes' inverse."""
    segments = empty_segments(int(expert[E_DEPTH]) // 2 + 2)
    count = path_segments(expert, stacks, branches, rising, scalars, segments, 0)
    return segments[:count]


@compiled()
def segment_length(segment, branches, p):
    """A path segment's curve at one pressure."""
    shape = branch_length(branches[int(segment[G_MAJOR])], p)
    if segment[G_ORIGIN] == 0.0:
        return shape
    return curve_length(shape, segment[G_L_ORIGIN], segment[G_L_TARGET], segment[G_B_ORIGIN],
                        segment[G_B_TARGET], segment[G_FLAT] != 0.0, segment[G_SHARE],
                        segment[G_KNEE])


@compiled()
def mixed_length(p, rising, experts, paths, segments, branches, scalars):
    """The mixture's settled length at p along the path (each expert's length on its path,
    drift applied, weighted; the local offset faded by the travel to p).
    paths[i]: (first, count) of expert i's segments."""
    total = 0.0
    for i in range(experts.shape[0]):
        expert = experts[i]
        weight = expert[E_WEIGHT]
        if not weight > 0.0:
            continue
        first, count = paths[i, 0], paths[i, 1]
        j = first
        while j < first + count:   # HysteresisModel.path_map
            segment = segments[j]
            if (p < segment[G_FROM]) if rising else (p > segment[G_FROM]):
                length = expert[E_LENGTH]   # the band's hold, before its branch is met
                break
            if (p <= segment[G_TO]) if rising else (p >= segment[G_TO]):
                length = segment_length(segment, branches, p)
                break
            j += 1
        else:   # beyond the last segment's end: its curve goes on
            length = segment_length(segments[first + count - 1], branches, p)
        total += weight * drifted_length(expert[E_REFERENCE], expert[E_SHIFT], expert[E_GAIN],
                                         length)
    return total + faded_offset(scalars[S_OFFSET], scalars[S_PLAY_AT], p,
                                scalars[S_HALF_PLAY], scalars[S_FADE])


@compiled()
def brentq(target, xa, xb, rising, experts, paths, segments, branches, scalars):
    """scipy's brentq.c on mixed_length(p) - target: (root, converged)."""
    xtol, rtol = scalars[S_XTOL], scalars[S_RTOL]
    xpre, xcur = xa, xb
    xblk, fblk, spre, scur = 0.0, 0.0, 0.0, 0.0
    fpre = mixed_length(xpre, rising, experts, paths, segments, branches, scalars) - target
    fcur = mixed_length(xcur, rising, experts, paths, segments, branches, scalars) - target
    if fpre == 0.0:
        return xpre, True
    if fcur == 0.0:
        return xcur, True
    if (fpre < 0.0) == (fcur < 0.0):
        return math.nan, False
    for _ in range(int(scalars[S_MAXITER])):
        if fpre != 0.0 and fcur != 0.0 and ((fpre < 0.0) != (fcur < 0.0)):
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2.0
        sbis = (xblk - xcur) / 2.0
        if fcur == 0.0 or abs(sbis) < delta:
            return xcur, True
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:   # secant
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:              # inverse quadratic interpolation
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2.0 * abs(stry) < min(abs(spre), 3.0 * abs(sbis) - delta):
                spre, scur = scur, stry
            else:
                spre, scur = sbis, sbis
        else:
            spre, scur = sbis, sbis
        xpre, fpre = xcur, fcur
        if abs(scur) > delta:
            xcur += scur
        else:
            xcur += delta if sbis > 0.0 else -delta
        fcur = mixed_length(xcur, rising, experts, paths, segments, branches, scalars) - target
    return xcur, False


@compiled()
def mixed_path_pressure(length_m, experts, stacks, branches, scalars):
    """RuleMix.pressure_for_length along the path (AUTO), after its delegations:
    (status, pressure, low, high, rising). status 1: found; 0: length_m is outside
    [low, high], what the path reaches from here to 0 Pa or the maximum; -1: the root find
    did not converge (scipy raises there)."""
    rising = length_m < scalars[S_SETTLED]
    n = experts.shape[0]
    capacity = 0
    for i in range(n):   # a path has at most one segment per two turning points, plus two
        capacity += int(experts[i, E_DEPTH]) // 2 + 2
    segments = empty_segments(capacity)
    paths = np.empty((n, 2), dtype=np.int64)
    for i in range(n):
        paths[i, 0], paths[i, 1] = 0, 0
    count = 0
    for i in range(n):
        if experts[i, E_WEIGHT] > 0.0:
            paths[i, 0] = count
            count = path_segments(experts[i], stacks, branches, rising, scalars, segments,
                                  count)
            paths[i, 1] = count - paths[i, 0]
    start = scalars[S_HERE]
    end = scalars[S_MAX] if rising else 0.0
    at_start = mixed_length(start, rising, experts, paths, segments, branches, scalars)
    at_end = mixed_length(end, rising, experts, paths, segments, branches, scalars)
    low, high = py_min(at_start, at_end), py_max(at_start, at_end)
    rounding = scalars[S_ROUNDING]
    if not low - rounding <= length_m <= high + rounding:
        return 0, math.nan, low, high, rising
    if abs(at_start - length_m) <= rounding:
        return 1, start, low, high, rising
    if abs(at_end - length_m) <= rounding:
        return 1, end, low, high, rising
    root, converged = brentq(length_m, min(start, end), max(start, end), rising, experts, paths,
                             segments, branches, scalars)
    return (1 if converged else -1), root, low, high, rising


def branch_table(rows) -> np.ndarray:
    """Branch rows stacked into one array, zero-padded to the longest."""
    table = np.zeros((len(rows), max(row.size for row in rows)))
    for i, row in enumerate(rows):
        table[i, :row.size] = row
    return table


def warm_up() -> None:
    """Compile what the model calls, or load it from the cache: a short run of the default
    `mix` on each branch form, its inverses, a learned correction and each rule's path, so
    that no process's first inverse waits seconds for the compiler (tools/setup.sh runs
    this after a build, which fills the cache)."""
    # Imported here: at module level this file imports nothing of pma_model (see above).
    from dataclasses import replace

    from pma_model.branches import BRANCH_FORMS
    from pma_model.correction import CORRECTION_KNOTS_PA, CorrectedBranch
    from pma_model.memory import HysteresisModel
    from pma_model.params import default_params
    from pma_model.rules import MEMORY_RULES

    for form in BRANCH_FORMS:
        params = replace(default_params(), branch_form=form)
        online = replace(params, memory='mix').build_online()
        for k, p_pa in enumerate((0.0, 2e5, 4e5, 1e5, 3e5, 2e5)):
            online.step(p_pa, float(params.build_model().increasing.length(p_pa)) + 1e-3,
                        0.02 * k)
        for branch in (0, 1, 2):
            online.pressure_for_length(0.27, branch)
        increasing, decreasing = params.branches()
        corrected = CorrectedBranch(increasing, (1e-4,) * len(CORRECTION_KNOTS_PA))
        corrected.inverse_unchecked(float(corrected.length(1e5)))
        for rule in MEMORY_RULES:
            model = HysteresisModel(corrected, decreasing, memory=rule)
            for p_pa in (3e5, 1e5, 2e5):
                model.update(p_pa)
            model.pressure_for_length(0.27)
            # The array forms (a recorded run's prediction, the fits, the figures).
            model.predict(np.linspace(0.0, 4e5, 5))
        online.drift.correct(np.linspace(0.25, 0.29, 3))
        corrected.inverse_unchecked(np.linspace(0.25, 0.29, 3))

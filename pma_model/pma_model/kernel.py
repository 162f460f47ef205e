"""The model's scalar formulas, compiled (numba), and the online step and the mix's inverse in
one call each.

Each formula has its one home here: a branch form's length and closed-form inverse, the knot
interpolation of the learned correction and its weights, a scanning curve's length, shapes and
gradient, where a reversal lies across the loop and its play share, the detector's rule, the
monotone bound, the creep lag, the share's least squares, the virgin term's knots, the local
offset's fade and update, the path pressure would follow from a state (the turning-point
stack's curves, or the friction band's hold), the mixed length along it and a root find
(scipy's brentq.c, step for step). The classes (branches.py, correction.py, curves.py,
detector.py, local_offset.py, identification.py) call them for one value; mix.RuleMix's
inverse calls `mixed_path_pressure` (along the path) or `mixed_major_pressure` (on the major
branches) once, with the state packed as arrays, and the online step
is `online_step` (one rule) or `mix_step` (a mix of rules) on each rule's state packed
as arrays (identification.OnlineModel._pack: the N_ and C_ layouts below), their Python twins
(OnlineModel.reference_step, RuleMix.reference_step) kept as the reference they are tested
against.

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


def elementwise(loop, values, *constants):
    """`loop` (one of the compiled loops over a 1-D array below: branch_lengths,
    branch_pressures, curve_lengths) applied to values of any shape; a float for a single
    value. Plain Python: it only lays the values out for the loop."""
    array = np.asarray(values, dtype=float)
    flat = array.ravel()
    if not flat.flags.writeable:   # numba compiles read-only arrays apart: keep one kind
        flat = flat.copy()
    result = loop(flat, *constants).reshape(array.shape)
    return float(result) if result.ndim == 0 else result


@compiled()
def branch_lengths(pressures, row):
    """branch_length at each of `pressures` (1-D): the array form of the same formula."""
    result = np.empty(pressures.size)
    for i in range(pressures.size):
        result[i] = branch_length(row, pressures[i])
    return result


@compiled()
def branch_pressures(lengths, row):
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
def drift_offset(reference_m, shift_m, gain):
    """The offset of drifted = offset + gain * model (adaptation.Drift.offset_m)."""
    return reference_m * (1.0 - gain) + shift_m


@compiled()
def drift_walk_variance(noise_m2, time_constant_s, dt_s):
    """The drift shift's random-walk variance for a step of dt_s: the walk whose steady Kalman
    gain remembers about time_constant_s (steps under a millisecond count as one, so a
    repeated time stamp does not make the walk infinite)."""
    samples = time_constant_s / py_max(dt_s, 1e-3)
    return noise_m2 / samples ** 2


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
    status, pressure, low, high = _mixed_root(
        length_m, scalars[S_HERE], scalars[S_MAX] if rising else 0.0, rising, experts, paths,
        segments, branches, scalars)
    return status, pressure, low, high, rising


@compiled()
def mixed_major_pressure(length_m, rising, experts, branches, scalars):
    """RuleMix.pressure_for_length on one direction's major branches (INCREASING,
    DECREASING), after its delegations: (status, pressure, low, high) as mixed_path_pressure's,
    each expert's path its major branch from 0 Pa to the maximum or back. Without the local
    offset (it belongs to the current state), whatever scalars hold."""
    n = experts.shape[0]
    segments = empty_segments(n)
    paths = np.empty((n, 2), dtype=np.int64)
    start, end = (0.0, scalars[S_MAX]) if rising else (scalars[S_MAX], 0.0)
    for i in range(n):
        segments[i, G_MAJOR] = experts[i, E_INCREASING] if rising else experts[i, E_DECREASING]
        segments[i, G_FROM], segments[i, G_TO] = start, end
        paths[i, 0], paths[i, 1] = i, 1
    plain = scalars.copy()
    plain[S_OFFSET] = 0.0
    return _mixed_root(length_m, start, end, rising, experts, paths, segments, branches, plain)


@compiled()
def _mixed_root(length_m, start, end, rising, experts, paths, segments, branches, scalars):
    """The pressure between start and end where the mixed length is length_m: (status,
    pressure, low, high) as mixed_path_pressure's, [low, high] the lengths at the ends."""
    at_start = mixed_length(start, rising, experts, paths, segments, branches, scalars)
    at_end = mixed_length(end, rising, experts, paths, segments, branches, scalars)
    low, high = py_min(at_start, at_end), py_max(at_start, at_end)
    rounding = scalars[S_ROUNDING]
    if not low - rounding <= length_m <= high + rounding:
        return 0, math.nan, low, high
    if abs(at_start - length_m) <= rounding:
        return 1, start, low, high
    if abs(at_end - length_m) <= rounding:
        return 1, end, low, high
    root, converged = brentq(length_m, min(start, end), max(start, end), rising, experts, paths,
                             segments, branches, scalars)
    return (1 if converged else -1), root, low, high


# --- the online step (identification.OnlineModel.step) ---------------------------------------

# A rule the compiled step runs (identification.KERNEL_RULES maps the rules' names to these).
RULE_MADELUNG, RULE_IDENTIFY, RULE_PLAY = 0.0, 1.0, 2.0

# An online model's state as the compiled step reads and moves it (OnlineModel._pack): the
# memory's (pressure, length, direction, the band's source, the detector, the stack's depth
# and how many of its turning points' gradients are kept, its play shares and slopes), then
# the learner's (clock, creep lags, counters, the share filters, the pressure travelled, what
# was last committed).
(N_P, N_L, N_RISING, N_PLAY_RISING, N_PLAY_P, N_BRANCH, N_EXTREME, N_COUNT, N_VALID,
 N_SHARE_UP, N_SHARE_DOWN, N_SLOPE_UP, N_SLOPE_DOWN, N_HAS_TIME, N_TIME, N_STATIC,
 N_LAGS_SET, N_SAMPLES, N_REJECTED, N_COMMITS) = range(20)
N_SHARES = 20        # [rising share, its slope, falling share, its slope] (the filter's)
N_SHARE_COVARIANCE = 24   # per direction [var share, covariance, var slope]
N_TRAVEL, N_TRAVEL_PLAY = 30, 31   # the pressure travelled since start, and its play
N_LAGS = 32          # the creep lags, then what was committed: 2K knots and 4 shares
# The step's constants (OnlineModel._kernel_config): the settings, the other modules'
# numbers, then blocks whose places the header gives.
(C_RULE, C_MAX_P, C_DEADBAND, C_INCREASING, C_DECREASING, C_LEARNING, C_DRIFTING,
 C_LEARNS_SHARE, C_REFERENCE, C_NOISE, C_OUTLIER, C_TIME_CONSTANT, C_MAX_STEP, C_MID_DEPTH,
 C_NARROW, C_FLAT_SPAN, C_COMMIT_M, C_COMMIT_SHARE, C_SPREAD_FLOOR, C_GAIN_WALK,
 C_WALK_SHARE, C_WALK_SLOPE, C_PRIOR_SHARE, C_PRIOR_SLOPE, C_MAX_POINTS, C_MAX_CORRECTION,
 C_CREEPS, C_VIRGINS, C_VIRGIN_END, C_TAUS_AT, C_CAPS_AT, C_WALK_AT, C_LOW_AT, C_HIGH_AT,
 C_VIRGIN_KNOTS_AT) = range(35)
CONFIG_HEAD = 35


@compiled()
def through_play(play, p, half_play):
    """Where a play of +/-half_play around p leaves its position `play` (the travel counted
    through it: the virgin term's, the local offset's)."""
    return py_min(py_max(play, p - half_play), p + half_play)


@compiled()
def elapsed(previous, t, max_step):
    """identification.elapsed_s between two known times: 0 if time went back, at most
    max_step (a pause is not a long sample)."""
    return py_min(py_max(t - previous, 0.0), max_step)


@compiled()
def creep_lag(lag, static, before, dt, tau):
    """A first-order lag of time constant tau moved over dt while the static length went
    from `before` to `static`, exact for a static length that moves linearly over the step."""
    slope = (static - before) / dt
    return static - slope * tau + (lag - before + slope * tau) * math.exp(-dt / tau)


@compiled()
def virgin_knot_share(knots, travel):
    """(k, share): the virgin term's hat weights at a travel within knots[0]..knots[-1] are
    1 - share at knot k and share at k + 1 (knots: the term's, then where it ends)."""
    k = 0
    while k + 2 < knots.size and knots[k + 1] <= travel:   # bisect_right - 1
        k += 1
    return k, (travel - knots[k]) / (knots[k + 1] - knots[k])


@compiled()
def share_update(share, slope, var_share, cov, var_slope, residual, h_share, h_slope, noise,
                 prior_share, prior_slope):
    """OnlineModel._learn_share's recursive least squares for one direction: (share, slope,
    var share, covariance, var slope) after a residual whose regressors are h_share and
    h_slope (the variances already walked). Bounded where it matters, the shares at both ends
    of the loop (depth 0 and 1) within 0..1 (clamping share and slope each on its own bent the
    learning), and never less sure than the prior (prior_*: its variances)."""
    spread_share = var_share * h_share + cov * h_slope
    spread_slope = cov * h_share + var_slope * h_slope
    innovation = noise + h_share * spread_share + h_slope * spread_slope
    gain_share, gain_slope = spread_share / innovation, spread_slope / innovation
    share = share + gain_share * residual
    slope = slope + gain_slope * residual
    near, far = share - 0.5 * slope, share + 0.5 * slope
    if not (0.0 <= near <= 1.0 and 0.0 <= far <= 1.0):
        near, far = py_min(1.0, py_max(0.0, near)), py_min(1.0, py_max(0.0, far))
        share, slope = 0.5 * (near + far), far - near
    var_share -= gain_share * spread_share
    cov -= gain_share * spread_slope
    var_slope -= gain_slope * spread_slope
    scale_share = math.sqrt(py_min(1.0, prior_share / py_max(var_share, 1e-300)))
    scale_slope = math.sqrt(py_min(1.0, prior_slope / py_max(var_slope, 1e-300)))
    return (share, slope, var_share * scale_share ** 2, cov * scale_share * scale_slope,
            var_slope * scale_slope ** 2)


@compiled()
def detector_step(branch, extreme, p, deadband, increasing, decreasing):
    """BranchDetector.update's rule: (branch, extreme) after pressure p. A reversal counts
    once pressure has moved deadband against the direction, from the extreme since the last."""
    if math.isnan(extreme):
        return branch, p
    moved = (extreme - p) if branch == increasing else (p - extreme)
    if moved > 0.0 and moved >= deadband:
        return (decreasing if branch == increasing else increasing), p
    if branch == increasing:
        return branch, py_max(extreme, p)
    return branch, py_min(extreme, p)


@compiled()
def monotone_offsets(values, caps, limit, out):
    """correction.monotone_correction into out: each offset within +/-limit and at most the
    previous one plus its interval's cap (from 0 Pa upward)."""
    low, high = -limit, limit
    previous = py_min(py_max(values[0], low), high)
    out[0] = previous
    for k in range(1, values.size):
        cap = previous + caps[k - 1]
        value = values[k]
        bounded = low if value < low else (high if value > high else value)
        previous = cap if bounded > cap else bounded
        out[k] = previous


@compiled()
def add_knot_weights(out, row, start, p):
    """correction.knot_sensitivity's weights: the row's branch at p as the knots' hat
    functions along its base length, added at out[start:]."""
    k, share = knot_share(row, p, base_length(row, p))
    out[start + k] = 1.0 - share
    if share != 0.0:
        out[start + k + 1] = share


@compiled()
def curve_gradient(out, shape_gradient, end_origin, end_target, at_origin, at_target, shape,
                   l_origin, l_target, b_origin, b_target, share, knee, knee_moves,
                   share_index):
    """ScanningCurve.gradient of a curve that is not flat, into out (its docstring has the
    formula); end_*: the gradients of the lengths at O and T, at_*: of the major branch at
    their pressures; share_index < 0: the rule has no share."""
    span = b_origin - b_target
    difference = l_origin - l_target
    raw = (shape - b_target) / span
    s, held = curve_coordinate(shape, b_target, b_origin, knee)
    linear = raw if share == 0.0 else s   # Madelung extrapolates, a mix clips
    mixed = share * held + (1.0 - share) * linear
    for i in range(out.size):
        out[i] = end_target[i] + (end_origin[i] - end_target[i]) * mixed
    if share == 0.0 or 0.0 < raw < 1.0:
        slope = (share / knee if s < knee else 0.0) + (1.0 - share)
        factor = difference * slope / span
        for i in range(out.size):
            out[i] += factor * (shape_gradient[i] - at_target[i]
                                - s * (at_origin[i] - at_target[i]))
    if share > 0.0 and s < knee and knee_moves:
        factor = difference * share * s / (knee * knee * span)
        for i in range(out.size):
            out[i] -= factor * ((end_origin[i] - end_target[i])
                                - knee * (at_origin[i] - at_target[i]))
    if share_index >= 0:
        out[share_index] += difference * (held - s)


@compiled()
def _sensitivity(out, rows, rising, p):
    """knot_sensitivity of the major branch `rising` says, into out (zeroed first)."""
    for i in range(out.size):
        out[i] = 0.0
    knots = int(rows[0, ROW_KNOTS])
    add_knot_weights(out, rows[0 if rising else 1], 0 if rising else knots, p)


@compiled()
def _stack_curve(numbers, config, rows, stack, count, rising):
    """The scanning curve from the top of stack[:count] (HysteresisModel._curve): (major row,
    has O, P_O, L_O, P_T, L_T, B(P_O), B(P_T), flat, knee, share, O's depth)."""
    major = 0 if rising else 1
    mid = config[C_MID_DEPTH]
    if count == 0:
        return major, False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, 1.0, 0.0, mid
    p_origin, l_origin = stack[count - 1, 0], stack[count - 1, 1]
    if count >= 2:
        p_target, l_target = stack[count - 2, 0], stack[count - 2, 1]
    else:   # toward the anchor at the end of the major branch
        p_target = config[C_MAX_P] if rising else 0.0
        l_target = branch_length(rows[major], p_target)
    share, depth = 0.0, mid
    b_origin = branch_length(rows[major], p_origin)
    if config[C_RULE] == RULE_IDENTIFY:
        depth = origin_depth(b_origin, branch_length(rows[1 - major], p_origin), l_origin,
                             config[C_NARROW])
        share = play_share(numbers[N_SHARE_UP] if rising else numbers[N_SHARE_DOWN],
                           numbers[N_SLOPE_UP] if rising else numbers[N_SLOPE_DOWN], depth, mid)
    b_target = branch_length(rows[major], p_target)
    flat, knee = curve_knee(l_origin, l_target, b_origin, b_target, config[C_FLAT_SPAN])
    return (major, True, p_origin, l_origin, p_target, l_target, b_origin, b_target, flat,
            knee, share, depth)


@compiled()
def _curve_length(curve, rows, p):
    """A _stack_curve's length at p (ScanningCurve.length)."""
    major, has_origin, _, l_origin, _, l_target, b_origin, b_target, flat, knee, share, _ = \
        curve
    shape = branch_length(rows[major], p)
    if not has_origin:
        return shape
    return curve_length(shape, l_origin, l_target, b_origin, b_target, flat, share, knee)


@compiled()
def _push(numbers, stack, p, length, max_points):
    """HysteresisModel._push: a turning point on the stack; overflow forgets the oldest loop."""
    count = int(numbers[N_COUNT])
    stack[count, 0], stack[count, 1] = p, length
    count += 1
    if count > max_points:
        for k in range(count - 2):
            stack[k, 0], stack[k, 1] = stack[k + 2, 0], stack[k + 2, 1]
        count -= 2
        numbers[N_VALID] = 0.0
    numbers[N_COUNT] = count


@compiled()
def madelung_step(numbers, config, rows, stack, p):
    """HysteresisModel._step_madelung: a reversal pushes a turning point, reaching the one
    below the top wipes out both, and the length follows the curve in force."""
    if p == numbers[N_P]:
        return
    rising = p > numbers[N_P]
    if rising != (numbers[N_RISING] != 0.0):
        _push(numbers, stack, numbers[N_P], numbers[N_L], int(config[C_MAX_POINTS]))
        numbers[N_RISING] = 1.0 if rising else 0.0
    count = int(numbers[N_COUNT])
    while count >= 2 and ((p >= stack[count - 2, 0]) if rising else (p <= stack[count - 2, 0])):
        count -= 2
    numbers[N_COUNT] = count
    numbers[N_VALID] = py_min(numbers[N_VALID], float(count))
    numbers[N_L] = _curve_length(_stack_curve(numbers, config, rows, stack, count, rising),
                                 rows, p)
    numbers[N_P] = p


@compiled()
def play_step(numbers, rows, p):
    """PlayRule.update: rising pressure shortens the length down to the increasing branch,
    falling lengthens it up to the decreasing one; the branch that set it is remembered."""
    if p > numbers[N_P]:
        bound = branch_length(rows[0], p)
        if bound <= numbers[N_L]:
            numbers[N_L], numbers[N_PLAY_RISING], numbers[N_PLAY_P] = bound, 1.0, p
        numbers[N_RISING] = 1.0
    elif p < numbers[N_P]:
        bound = branch_length(rows[1], p)
        if bound >= numbers[N_L]:
            numbers[N_L], numbers[N_PLAY_RISING], numbers[N_PLAY_P] = bound, 0.0, p
        numbers[N_RISING] = 0.0
    numbers[N_P] = p


@compiled()
def _point_gradient(out, numbers, config, rows, stack, gradients, count, rising, p, scratch):
    """d length / d parameters at pressure p on the curve from the top of stack[:count]
    (MadelungRule.length_gradient for the curve in force, _turning_point_gradients for a
    turning point); gradients[:count]: the turning points' own."""
    curve = _stack_curve(numbers, config, rows, stack, count, rising)
    major, has_origin, p_origin, l_origin, p_target, l_target, b_origin, b_target, flat, \
        knee, share, _ = curve
    shape_gradient, at_origin, at_target = scratch[0], scratch[1], scratch[2]
    _sensitivity(shape_gradient, rows, rising, p)
    if not has_origin:
        for i in range(out.size):
            out[i] = shape_gradient[i]
        return
    _sensitivity(at_origin, rows, rising, p_origin)
    _sensitivity(at_target, rows, rising, p_target)
    end_origin = gradients[count - 1]
    end_target = gradients[count - 2] if count >= 2 else at_target
    if flat:
        for i in range(out.size):
            out[i] = end_origin[i] + shape_gradient[i] - at_origin[i]
        return
    share_index = -1
    if config[C_RULE] == RULE_IDENTIFY:
        share_index = out.size - 2 if rising else out.size - 1
    curve_gradient(out, shape_gradient, end_origin, end_target, at_origin, at_target,
                   branch_length(rows[major], p), l_origin, l_target, b_origin, b_target,
                   share, knee, knee < 1.0, share_index)


@compiled()
def length_gradient(out, numbers, config, rows, stack, gradients, scratch):
    """HysteresisModel.length_gradient into out: the band's, at the branch and pressure its
    length was set at; the stack rules', exact through every turning point (their gradients
    kept in `gradients` while the stack below them is the same)."""
    if config[C_RULE] == RULE_PLAY:
        _sensitivity(out, rows, numbers[N_PLAY_RISING] != 0.0, numbers[N_PLAY_P])
        return
    count = int(numbers[N_COUNT])
    rising = numbers[N_RISING] != 0.0
    for depth in range(int(numbers[N_VALID]), count):
        # Turning points alternate: the top was reached moving against the current way.
        arriving = rising if (count - 1 - depth) % 2 else not rising
        _point_gradient(gradients[depth], numbers, config, rows, stack, gradients, depth,
                        arriving, stack[depth, 0], scratch)
    numbers[N_VALID] = count
    _point_gradient(out, numbers, config, rows, stack, gradients, count, rising, numbers[N_P],
                    scratch)


@compiled()
def _replay(numbers, config, rows, stack):
    """HysteresisModel.relearn with the rows' branches: the state rebuilt from rest through
    the remembered turning points (the stack rules) or the held length kept inside the new
    band (the band's)."""
    old_p, old_l, old_rising = numbers[N_P], numbers[N_L], numbers[N_RISING]
    count = int(numbers[N_COUNT])
    numbers[N_P], numbers[N_L], numbers[N_RISING] = 0.0, branch_length(rows[0], 0.0), 1.0
    numbers[N_COUNT], numbers[N_VALID] = 0.0, 0.0
    if config[C_RULE] != RULE_PLAY:
        numbers[N_PLAY_RISING], numbers[N_PLAY_P] = 1.0, 0.0
        pressures = np.empty(count)
        for k in range(count):
            pressures[k] = stack[k, 0]
        for k in range(count):
            madelung_step(numbers, config, rows, stack, pressures[k])
        madelung_step(numbers, config, rows, stack, old_p)
        return
    numbers[N_P], numbers[N_RISING] = old_p, old_rising   # PlayRule.resume
    low, high = branch_length(rows[1], old_p), branch_length(rows[0], old_p)
    numbers[N_L] = py_min(py_max(old_l, low), high)
    if not low < old_l < high:   # moved onto a branch by the new band
        numbers[N_PLAY_RISING], numbers[N_PLAY_P] = (1.0 if old_l >= high else 0.0), old_p


@compiled()
def learn_share(numbers, config, rising, depth, residual, difference, noise, dt):
    """OnlineModel._learn_share: recursive least squares on the current direction's share and
    slope, kept so that the shares at both ends of the loop are within 0..1, and never less
    sure than the prior."""
    if difference == 0.0:
        return
    at = N_SHARES + (0 if rising else 2)
    cov_at = N_SHARE_COVARIANCE + (0 if rising else 3)
    numbers[at], numbers[at + 1], numbers[cov_at], numbers[cov_at + 1], numbers[cov_at + 2] = \
        share_update(numbers[at], numbers[at + 1], numbers[cov_at] + config[C_WALK_SHARE] * dt,
                     numbers[cov_at + 1], numbers[cov_at + 2] + config[C_WALK_SLOPE] * dt,
                     residual, difference, difference * (depth - config[C_MID_DEPTH]), noise,
                     config[C_PRIOR_SHARE], config[C_PRIOR_SLOPE])


@compiled()
def _commit_if_moved(numbers, config, mean, rows, stack):
    """OnlineModel._commit_if_moved: once the branch correction or a share has moved far
    enough, new branches (mean +/- half the difference, each bounded and monotone) and
    shares, and the state replayed with them."""
    knots = int(rows[0, ROW_KNOTS])
    committed = N_LAGS + int(config[C_CREEPS])
    moved = False
    for i in range(2 * knots):
        if not abs(mean[i] - numbers[committed + i]) < config[C_COMMIT_M]:
            moved = True
    for i in range(4):
        if not abs(numbers[N_SHARES + i] - numbers[committed + 2 * knots + i]) < \
                config[C_COMMIT_SHARE]:
            moved = True
    if not moved:
        return
    for i in range(2 * knots):
        numbers[committed + i] = mean[i]
    for i in range(4):
        numbers[committed + 2 * knots + i] = numbers[N_SHARES + i]
    values = np.empty(knots)
    offsets = ROW_HEAD + 2 * knots
    caps_at = int(config[C_CAPS_AT])
    for branch in range(2):
        half = 0.5 if branch == 0 else -0.5
        for k in range(knots):
            values[k] = mean[k] + half * mean[knots + k]
        monotone_offsets(values, config[caps_at + branch * (knots - 1):
                                        caps_at + (branch + 1) * (knots - 1)],
                         config[C_MAX_CORRECTION], rows[branch, offsets:offsets + knots])
    numbers[N_COMMITS] += 1.0
    numbers[N_SHARE_UP], numbers[N_SHARE_DOWN] = numbers[N_SHARES], numbers[N_SHARES + 2]
    numbers[N_SLOPE_UP], numbers[N_SLOPE_DOWN] = numbers[N_SHARES + 1], numbers[N_SHARES + 3]
    _replay(numbers, config, rows, stack)


@compiled()
def advance_lags(numbers, config, static, t, has_t):
    """OnlineModel._advance_lags: the creep lags moved to time t (exact for a static length
    that moves linearly over the step); the step [s], 0 when a time is unknown, at most
    C_MAX_STEP."""
    creeps, taus = int(config[C_CREEPS]), int(config[C_TAUS_AT])
    if numbers[N_LAGS_SET] == 0.0 or not has_t or numbers[N_HAS_TIME] == 0.0:
        dt = 0.0
        if numbers[N_LAGS_SET] == 0.0:
            for j in range(creeps):
                numbers[N_LAGS + j] = static
            numbers[N_LAGS_SET] = 1.0
    else:
        dt = elapsed(numbers[N_TIME], t, config[C_MAX_STEP])
    if dt > 0.0:
        for j in range(creeps):
            numbers[N_LAGS + j] = creep_lag(numbers[N_LAGS + j], static, numbers[N_STATIC], dt,
                                            config[taus + j])
    if has_t:
        numbers[N_HAS_TIME], numbers[N_TIME] = 1.0, t
    numbers[N_STATIC] = static
    return dt


@compiled()
def _learn(numbers, config, mean, covariance, rows, stack, gradients, residual, undrifted,
           shape_difference, depth, gain, dt, virgin_k, virgin_share):
    """OnlineModel._learn: one Kalman update of the state (the branch correction and its
    difference through the length's exact gradient, creep, the virgin term, drift), the share
    filter, the correction kept monotone and everything bounded, then a commit if it moved."""
    if abs(residual) > config[C_OUTLIER]:
        numbers[N_REJECTED] += 1.0
        return
    noise = config[C_NOISE]
    rising = numbers[N_RISING] != 0.0
    if config[C_LEARNS_SHARE] != 0.0:
        learn_share(numbers, config, rising, depth, residual, shape_difference * gain, noise,
                    dt)
    knots = int(rows[0, ROW_KNOTS])
    creeps, virgins = int(config[C_CREEPS]), int(config[C_VIRGINS])
    size = mean.size
    scratch = np.empty((4, 2 * knots + 2))
    gradient = scratch[3]
    length_gradient(gradient, numbers, config, rows, stack, gradients, scratch)
    regressor = np.empty(size)
    for k in range(knots):
        increasing, decreasing = gradient[k], gradient[knots + k]
        regressor[k] = (increasing + decreasing) * gain
        regressor[knots + k] = (increasing - decreasing) * (0.5 * gain)
    creep_at = 2 * knots
    for j in range(creeps):
        regressor[creep_at + j] = gain * (numbers[N_LAGS + j] - numbers[N_STATIC])
    virgin_at = creep_at + creeps
    if virgins > 0:   # (virgin_k < 0: it ends at this sample, its rows not yet dropped)
        for j in range(virgins):
            regressor[virgin_at + j] = 0.0
        if virgin_k >= 0:
            regressor[virgin_at + virgin_k] = gain * (1.0 - virgin_share)
            if virgin_share != 0.0 and virgin_k + 1 < virgins:
                regressor[virgin_at + virgin_k + 1] = gain * virgin_share
    regressor[size - 2] = 1.0
    regressor[size - 1] = undrifted - config[C_REFERENCE]
    walk_at = int(config[C_WALK_AT])
    drift_walk = 0.0
    if config[C_DRIFTING] != 0.0:
        drift_walk = drift_walk_variance(noise, config[C_TIME_CONSTANT], dt)
    for i in range(size):
        walk = config[walk_at + i] * dt
        if config[C_DRIFTING] != 0.0 and i >= size - 2:
            walk = drift_walk if i == size - 2 else drift_walk / config[C_GAIN_WALK]
        covariance[i, i] += walk
    spread = np.empty(size)
    innovation = 0.0
    for i in range(size):
        total = 0.0
        for j in range(size):
            total += covariance[i, j] * regressor[j]
        spread[i] = total
    for i in range(size):
        innovation += regressor[i] * spread[i]
    innovation = noise / py_max(1.0, config[C_SPREAD_FLOOR]) + innovation
    step = residual / innovation
    for i in range(size):
        mean[i] = mean[i] + spread[i] * step
    for i in range(size):
        for j in range(size):
            covariance[i, j] -= spread[i] * spread[j] / innovation
    # The mean correction kept monotone on both branches, the rest bounded value by value.
    monotone_offsets(mean[:knots].copy(), config[int(config[C_CAPS_AT]) + 2 * (knots - 1):],
                     config[C_MAX_CORRECTION], mean[:knots])
    low_at, high_at = int(config[C_LOW_AT]), int(config[C_HIGH_AT])
    for i in range(knots, size):
        value = py_max(mean[i], config[low_at + i - knots])
        mean[i] = py_min(value, config[high_at + i - knots])
    numbers[N_SAMPLES] += 1.0
    _commit_if_moved(numbers, config, mean, rows, stack)


@compiled()
def advance_travel(numbers, config, p):
    """OnlineModel._advance_travel: the pressure travelled since start, through a play of the
    deadband's width; (k, share) of the virgin term's knots there (virgin_knot_weights' two
    weights), k = -1 once the term has ended, -2 when it ends at this sample."""
    virgins = int(config[C_VIRGINS])
    if virgins == 0:
        return -1, 0.0
    half = 0.5 * config[C_DEADBAND]
    if math.isnan(numbers[N_TRAVEL_PLAY]):
        numbers[N_TRAVEL_PLAY] = p
    play = numbers[N_TRAVEL_PLAY]
    moved = through_play(play, p, half)
    numbers[N_TRAVEL] += abs(moved - play)
    numbers[N_TRAVEL_PLAY] = moved
    travel = numbers[N_TRAVEL]
    if travel >= config[C_VIRGIN_END]:
        return -2, 0.0
    at = int(config[C_VIRGIN_KNOTS_AT])   # the knots, then the end
    return virgin_knot_share(config[at:at + virgins + 1], travel)


@compiled()
def online_step(p, measured, t, has_t, numbers, config, mean, covariance, rows, stack,
                gradients):
    """OnlineModel.step for a finite pressure, in place on its packed state: the memory moves,
    creep, the virgin term and drift give the prediction, then it learns from the measured
    length (NaN: nothing to learn). (predicted, branch, static, drift's offset, drift's gain,
    whether the virgin term ended: the caller drops it from the filter, whose rows of it
    this step left alone, as their regressor was 0)."""
    virgin_k, virgin_share = advance_travel(numbers, config, p)
    size = mean.size
    reference = config[C_REFERENCE]
    shift, gain = mean[size - 2], 1.0 + mean[size - 1]
    offset = drift_offset(reference, shift, gain)
    branch, extreme = detector_step(numbers[N_BRANCH], numbers[N_EXTREME], p,
                                    config[C_DEADBAND], config[C_INCREASING],
                                    config[C_DECREASING])
    numbers[N_BRANCH], numbers[N_EXTREME] = branch, extreme
    if config[C_RULE] == RULE_PLAY:
        play_step(numbers, rows, p)
    else:
        madelung_step(numbers, config, rows, stack, p)
    static = numbers[N_L]
    dt = advance_lags(numbers, config, static, t, has_t)
    knots = int(rows[0, ROW_KNOTS])
    creeps = int(config[C_CREEPS])
    total = 0.0
    for j in range(creeps):
        total += mean[2 * knots + j] * (numbers[N_LAGS + j] - static)
    undrifted = static + total
    if virgin_k >= 0:
        virgin_at = 2 * knots + creeps
        later = 0.0
        if virgin_share != 0.0 and virgin_k + 1 < int(config[C_VIRGINS]):
            later = virgin_share * mean[virgin_at + virgin_k + 1]
        undrifted += (1.0 - virgin_share) * mean[virgin_at + virgin_k] + later
    predicted = drifted_length(reference, shift, gain, undrifted)
    if (config[C_LEARNING] != 0.0 or config[C_DRIFTING] != 0.0) and math.isfinite(measured):
        shape_difference, depth = 0.0, config[C_MID_DEPTH]
        if config[C_LEARNS_SHARE] != 0.0:   # the two shapes 'identify' mixes, here
            curve = _stack_curve(numbers, config, rows, stack, int(numbers[N_COUNT]),
                                 numbers[N_RISING] != 0.0)
            major, has_origin, _, l_origin, _, l_target, b_origin, b_target, flat, knee, \
                _, depth = curve
            if has_origin:
                play, madelung = curve_shapes(branch_length(rows[major], p), l_origin,
                                              l_target, b_origin, b_target, flat, knee)
                shape_difference = play - madelung
        _learn(numbers, config, mean, covariance, rows, stack, gradients, measured - predicted,
               undrifted, shape_difference, depth, gain, dt, virgin_k, virgin_share)
    return predicted, branch, static, offset, gain, virgin_k == -2


# --- the mix's step (mix.RuleMix.step) --------------------------------------------------------

# The mix's constants (RuleMix._mix_constants): its settings and the other modules' numbers.
(X_TEMPERATURE, X_TIME_CONSTANT, X_CAP, X_HALF_PLAY, X_FADE, X_WALK, X_MAX_STEP) = range(7)
MIX_CONSTANTS = 7
# A rule's prediction in the mix's outputs (RuleMix.last_predictions).
(P_LENGTH, P_BRANCH, P_STATIC, P_OFFSET, P_GAIN) = range(5)


@compiled()
def local_advance(offset, variance, play, p, half_play, fade_pa, walk):
    """LocalOffset.advance: (offset, variance, play) once pressure has moved to p, the
    offset fading and loosening by the travel through the play."""
    if math.isnan(play):
        play = p
    moved = through_play(play, p, half_play)
    travel = abs(moved - play)
    if travel > 0.0:
        fade = math.exp(-travel / fade_pa)
        offset *= fade
        variance = fade * fade * variance + walk * travel
    return offset, variance, moved


@compiled()
def local_learn(offset, variance, residual, noise_m2, outlier):
    """LocalOffset.learn: (offset, variance) after a residual (measured - the mix's length
    before the offset), a scalar Kalman update."""
    if not abs(residual) <= outlier or variance <= 0.0:
        return offset, variance
    gain = variance / (variance + noise_m2)
    return offset + gain * (residual - offset), variance * (1.0 - gain)


@compiled()
def mix_step(p, measured, t, has_t, learning, local_on, local_offset, local_variance,
             local_play, local_noise_m2, local_outlier, mix, losses, outputs, numbers, configs,
             means, covariances, rows, stacks, gradients):
    """RuleMix.step for a finite pressure: every rule's online_step (its packed arrays, one
    per tuple), their mixture by the weights before it (from `losses`, which learn in
    place, when `learning`), the local offset (local_*, LocalOffset's) moving and learning
    (when local_on too); `mix`: the constants (X_ layout). (length, branch, static, offset,
    gain, local offset, a bit per rule whose virgin term ended, the local offset's offset,
    variance and play after the step); each rule's prediction into outputs (P_ layout)."""
    rules = len(numbers)
    least = losses[0]
    for i in range(1, rules):
        least = py_min(least, losses[i])
    weights = np.empty(rules)
    total = 0.0
    for i in range(rules):
        weights[i] = math.exp(-(losses[i] - least) / mix[X_TEMPERATURE])
        total += weights[i]
    for i in range(rules):
        weights[i] = weights[i] / total
    had_time, previous = numbers[0][N_HAS_TIME] != 0.0, numbers[0][N_TIME]
    ended = 0
    for i in range(rules):
        length, branch, static, offset, gain, virgin_ended = online_step(
            p, measured, t, has_t, numbers[i], configs[i], means[i], covariances[i], rows[i],
            stacks[i], gradients[i])
        outputs[i, P_LENGTH], outputs[i, P_BRANCH], outputs[i, P_STATIC] = length, branch, static
        outputs[i, P_OFFSET], outputs[i, P_GAIN] = offset, gain
        if virgin_ended:
            ended |= 1 << i
    dt = 0.0
    if had_time and has_t:   # identification.elapsed_s
        dt = elapsed(previous, t, mix[X_MAX_STEP])
    if learning and math.isfinite(measured) and dt > 0.0:
        cap = mix[X_CAP]   # an outlier counts as the limit the rules reject it at
        useful = False
        for i in range(rules):
            if abs(outputs[i, P_LENGTH] - measured) <= cap:
                useful = True
        if useful:   # one every rule rejects says nothing
            forget = math.exp(-dt / mix[X_TIME_CONSTANT])
            for i in range(rules):
                error = py_min(abs(outputs[i, P_LENGTH] - measured), cap)
                losses[i] = losses[i] * forget + error ** 2 * dt
    offset_m, variance, play = local_advance(local_offset, local_variance, local_play, p,
                                             mix[X_HALF_PLAY], mix[X_FADE], mix[X_WALK])
    local = offset_m
    mixed, static, offset, gain = 0.0, 0.0, 0.0, 0.0
    for i in range(rules):
        mixed += weights[i] * outputs[i, P_LENGTH]
    for i in range(rules):
        static += weights[i] * outputs[i, P_STATIC]
    for i in range(rules):
        offset += weights[i] * outputs[i, P_OFFSET]
    for i in range(rules):
        gain += weights[i] * outputs[i, P_GAIN]
    if learning and local_on and math.isfinite(measured):
        offset_m, variance = local_learn(offset_m, variance, measured - mixed, local_noise_m2,
                                         local_outlier)
    return (mixed + local, outputs[0, P_BRANCH], static, offset, gain, local, ended, offset_m,
            variance, play)


def branch_table(rows) -> np.ndarray:
    """Branch rows stacked into one array, zero-padded to the longest."""
    table = np.zeros((len(rows), max(row.size for row in rows)))
    for i, row in enumerate(rows):
        table[i, :row.size] = row
    return table


def warm_up() -> None:
    """Compile what the model calls, or load it from the cache: a short run of the default
    `mix` on each branch form (its compiled step, and the Python one the tests compare it
    with), each rule's own compiled step, its inverses, a learned correction and each rule's
    path, so that no process's first step or inverse waits seconds for the compiler
    (tools/setup.sh runs this after a build, which fills the cache)."""
    # Imported here: at module level this file imports nothing of pma_model (see above).
    from dataclasses import replace

    from pma_model.branches import BRANCH_FORMS
    from pma_model.correction import CORRECTION_KNOTS_PA, CorrectedBranch
    from pma_model.memory import HysteresisModel
    from pma_model.params import default_params
    from pma_model.rules import MEMORY_RULES

    for form in BRANCH_FORMS:
        params = replace(default_params(), branch_form=form)
        samples = [(p_pa, float(params.build_model().increasing.length(p_pa)) + 1e-3, 0.02 * k)
                   for k, p_pa in enumerate((0.0, 2e5, 4e5, 1e5, 3e5, 2e5, 6e5, 1e5))]
        for memory in ('identify', 'play', 'mix'):   # the mix last: its inverses below
            online = replace(params, memory=memory).build_online()
            reference = replace(params, memory=memory).build_online()
            for sample in samples:
                online.step(*sample)
                reference.reference_step(*sample)
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

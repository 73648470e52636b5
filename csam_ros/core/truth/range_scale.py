"""Relative camera range scales from mutual rendezvous, without ground truth.

Each camera measures ranges with its own scale error ``s_i = measured / true``. When robot
``a`` measures its range to robot ``b`` and ``b`` its range to ``a`` at (nearly) the same
time, both measure the same distance ``d`` (camera to the other robot's barcode; with
identical robots any offset of camera or barcode from the robot centre is the same on both
sides). A camera that derives range from the image height of a barcode measures depth along
its optical axis, ``d cos(beta)`` at bearing ``beta``, not the distance; with an exponent
``c`` (``c = 1``: pure depth, ``c = 0``: distance) the model is

    r_ab = s_a d cos(beta_ab)^c,  r_ba = s_b d cos(beta_ba)^c

    =>   y = log r_ab - log r_ba = (log s_a - log s_b) + c z,
         z = log cos(beta_ab) - log cos(beta_ba).

:func:`mutual_pairs` forms ``y`` and ``z`` for one pair of robots: each measurement of one
robot is matched with the other robot's log range (and log cos bearing) interpolated
linearly to its stamp (between two measurements at most ``max_gap`` apart that bracket it,
or the nearest one within ``tolerance``). :func:`mutual_range_scales` solves, over all pairs
``k`` of all robot pairs,

    min_{x, c}  sum_k w_k rho((y_k - (x_a(k) - x_b(k)) - c z_k) / sigma),   x_i = log s_i,

with ``c`` either given or fitted as one unknown common to all cameras, by iteratively
reweighted least squares with a Cauchy kernel ``rho`` (``sigma`` the normalised median
absolute deviation of the residuals). The weighted normal equations of ``x`` are a graph
Laplacian ``L``, singular along each connected component's indicator vector (adding a
constant to its ``x`` changes no residual); the minimum-norm solution (pseudo-inverse of the
normal matrix, with or without ``c``) is orthogonal to those and so fixes the gauge that only
relative scales are observable: ``sum_i x_i = 0`` in each connected component of the graph
of robots that met, i.e. the geometric mean of the scales is 1 there. The covariance is
``sigma^2`` times the pseudo-inverse of the normal matrix (pairs taken as independent). A
robot without any mutual pair gets no scale (it is listed in ``RangeScaleEstimate.unpaired``),
never an invented 1.0. Pairs of one meeting are not independent: :func:`meeting_jackknife`
gives standard errors from leaving out whole meetings.

Mutual pairs see ``s_i / t_i`` if the robots' barcodes differ (``t_i``: the scale error of
ranges *to* robot ``i``); nothing in the pairs separates the two. :func:`map_range_scales`
is the other truth-free route: every robot's landmark ranges against one common map, for
example C-SAM's joined map (:func:`reference_from_joined_map`), whose own scale cancels in
the relative scales.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

from csam_ros.core.model.log import FeatureLog, GroundTruth, MultiRobotLog
from csam_ros.core.truth.calibration import range_scale
from csam_ros.core.truth.localisation import localise
from csam_ros.core.truth.noise_model import NoiseModel, robust_sigma
from csam_ros.core.truth.snapshots import snapshot_localisation

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class MutualPairs:
    """Mutual range pairs of robots ``a`` and ``b`` (:func:`mutual_pairs`)."""

    stamps: FloatArray  # (K,) stamp of the anchoring measurement
    log_ratio: FloatArray  # (K,) y = log r_ab - log r_ba
    log_cos_ratio: FloatArray  # (K,) z = log cos beta_ab - log cos beta_ba (0 without bearings)

    def __len__(self) -> int:
        return int(self.stamps.size)


def mutual_pairs(
    stamps_ab: FloatArray,
    ranges_ab: FloatArray,
    stamps_ba: FloatArray,
    ranges_ba: FloatArray,
    bearings_ab: FloatArray | None = None,
    bearings_ba: FloatArray | None = None,
    max_gap: float = 0.5,
    tolerance: float = 0.05,
    both_directions: bool = True,
) -> MutualPairs:
    """Mutual range pairs of robots ``a`` and ``b``: ``y = log r_ab(t) - log r_ba(t)`` and
    ``z = log cos beta_ab(t) - log cos beta_ba(t)`` (module docstring).

    ``stamps_ab, ranges_ab, bearings_ab`` are robot ``a``'s measurements of ``b`` (sorted by
    stamp), ``..._ba`` ``b``'s of ``a``; without bearings ``z = 0``. Each measurement of
    ``a`` at ``t`` is paired with ``b``'s values at ``t``: interpolated linearly between
    ``b``'s measurements at ``t0 <= t <= t1`` when ``t1 - t0 <= max_gap``, else ``b``'s
    nearest measurement when it is within ``tolerance`` seconds, else not paired. With
    ``both_directions`` each measurement of ``b`` is paired the same way with ``a``'s values,
    and the pairs of both directions are returned sorted by stamp (same sign convention:
    ``a`` over ``b``; the two directions share measurements, so they are not independent).
    """
    if (bearings_ab is None) != (bearings_ba is None):
        raise ValueError("give the bearings of both robots or of neither")
    cos_ab = _log_cos(bearings_ab, ranges_ab)
    cos_ba = _log_cos(bearings_ba, ranges_ba)
    t, y, z = _one_direction(
        stamps_ab, ranges_ab, cos_ab, stamps_ba, ranges_ba, cos_ba, max_gap, tolerance
    )
    if both_directions:
        tb, yb, zb = _one_direction(
            stamps_ba, ranges_ba, cos_ba, stamps_ab, ranges_ab, cos_ab, max_gap, tolerance
        )
        t, y, z = np.concatenate([t, tb]), np.concatenate([y, -yb]), np.concatenate([z, -zb])
        order = np.argsort(t, kind="stable")
        t, y, z = t[order], y[order], z[order]
    return MutualPairs(t, y, z)


def _log_cos(bearings: FloatArray | None, ranges: FloatArray) -> FloatArray:
    """``log cos(bearing)`` (zeros without bearings); bearings must lie within +-pi/2."""
    if bearings is None:
        return np.zeros(np.shape(ranges))
    b = np.asarray(bearings, dtype=float)
    if b.shape != np.shape(ranges):
        raise ValueError("bearings and ranges differ in length")
    if np.any(np.abs(b) >= np.pi / 2):
        raise ValueError("a bearing at or beyond +-pi/2 has no depth")
    return np.log(np.cos(b))


def _one_direction(
    stamps_ab: FloatArray,
    ranges_ab: FloatArray,
    cos_ab: FloatArray,
    stamps_ba: FloatArray,
    ranges_ba: FloatArray,
    cos_ba: FloatArray,
    max_gap: float,
    tolerance: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Pairs anchored on ``a``'s measurements (:func:`mutual_pairs`)."""
    t = np.asarray(stamps_ab, dtype=float)
    tb = np.asarray(stamps_ba, dtype=float)
    if t.size == 0 or tb.size == 0:
        return np.empty(0), np.empty(0), np.empty(0)
    log_a = np.log(np.asarray(ranges_ab, dtype=float))
    log_b = np.log(np.asarray(ranges_ba, dtype=float))
    after = np.searchsorted(tb, t, side="left")  # first b stamp >= t
    lo = np.clip(after - 1, 0, tb.size - 1)
    hi = np.clip(after, 0, tb.size - 1)
    exact = (after < tb.size) & (tb[hi] == t)
    lo = np.where(exact, hi, lo)
    bracket = exact | ((after > 0) & (after < tb.size) & (tb[hi] - tb[lo] <= max_gap))
    span = tb[hi] - tb[lo]
    frac = np.where(span > 0, (t - tb[lo]) / np.where(span > 0, span, 1.0), 0.0)
    nearest = np.where(np.abs(tb[lo] - t) <= np.abs(tb[hi] - t), lo, hi)
    close = ~bracket & (np.abs(tb[nearest] - t) <= tolerance)
    keep = bracket | close

    def at_t(values: FloatArray) -> FloatArray:
        inner = values[lo] + frac * (values[hi] - values[lo])
        return np.where(bracket, inner, values[nearest])[keep]

    return t[keep], log_a[keep] - at_t(log_b), cos_ab[keep] - at_t(cos_ba)


@dataclass
class RangeScaleEstimate:
    """Relative range scales of the robots' cameras (:func:`mutual_range_scales`)."""

    robots: list[str]  # all robots asked about
    scales: dict[str, float]  # robot -> s (geometric mean 1 per component); paired robots only
    log_sigma: dict[str, float]  # robot -> standard error of log s (same gauge)
    exponent: float  # c: given, or fitted (module docstring)
    exponent_sigma: float  # its standard error (0 when given)
    pairs: dict[tuple[str, str], int]  # (a, b), a before b in ``robots`` -> pairs used
    pair_log_ratio: dict[tuple[str, str], float]  # (a, b) -> fitted log s_a - log s_b
    pair_median: dict[tuple[str, str], float]  # (a, b) -> median of its own y - c z
    sigma: float  # robust spread of the residuals y - (x_a - x_b) - c z
    outliers: int  # pairs whose final residual exceeds 3 sigma (down-weighted by the kernel)
    components: list[list[str]]  # robots connected by pairs; each has its own gauge
    unpaired: list[str] = field(default_factory=list)  # robots without any mutual pair

    def rescaled(self, reference: Mapping[str, float]) -> dict[str, float]:
        """The scales multiplied by one factor per component so that their geometric mean
        over the robots also in ``reference`` equals ``reference``'s there: the relative
        part alone, to compare with scales fitted in another gauge."""
        out: dict[str, float] = {}
        for component in self.components:
            common = [r for r in component if r in reference]
            if not common:
                continue
            shift = np.mean([np.log(reference[r]) - np.log(self.scales[r]) for r in common])
            out.update({r: float(self.scales[r] * np.exp(shift)) for r in component})
        return out


def mutual_range_scales(
    robots: Sequence[str],
    pairs: Mapping[tuple[str, str], MutualPairs],
    weight: float = 1.0,
    exponent: float | None = 0.0,
    threshold: float = 2.385,
    iterations: int = 100,
) -> RangeScaleEstimate:
    """Range scales ``s_i`` (up to one common factor per connected group of robots) from
    mutual pairs (:func:`mutual_pairs`); equations in the module docstring.

    ``pairs[(a, b)]`` holds the pairs of robots ``a`` and ``b`` (either order: a key
    ``(b, a)`` is read with its signs flipped). ``weight`` multiplies every pair's weight
    (e.g. 1/2 when both directions of :func:`mutual_pairs` are used, whose pairs share
    measurements: it only widens the standard errors). ``exponent`` is the depth exponent
    ``c``, or None to fit it (needs bearings, i.e. ``z`` not all zero). Cauchy kernel at
    ``threshold`` robust sigmas.
    """
    names = list(robots)
    n = len(names)
    index = {name: k for k, name in enumerate(names)}
    parts: list[tuple[int, int, FloatArray, FloatArray]] = []
    for (a, b), p in pairs.items():
        if a not in index or b not in index:
            raise ValueError(f"pair ({a!r}, {b!r}) names a robot not in {names}")
        if a == b:
            raise ValueError(f"pair ({a!r}, {b!r}): a robot cannot pair with itself")
        y, z = np.asarray(p.log_ratio, dtype=float), np.asarray(p.log_cos_ratio, dtype=float)
        good = np.isfinite(y) & np.isfinite(z)
        y, z = y[good], z[good]
        if index[a] > index[b]:
            a, b, y, z = b, a, -y, -z
        if y.size:
            parts.append((index[a], index[b], y, z))
    i = (
        np.concatenate([np.full(y.size, a) for a, _, y, _ in parts]).astype(np.int64)
        if parts
        else np.empty(0, np.int64)
    )
    j = (
        np.concatenate([np.full(y.size, b) for _, b, y, _ in parts]).astype(np.int64)
        if parts
        else np.empty(0, np.int64)
    )
    y = np.concatenate([p[2] for p in parts]) if parts else np.empty(0)
    z = np.concatenate([p[3] for p in parts]) if parts else np.empty(0)
    paired = np.zeros(n, dtype=bool)
    paired[i] = True
    paired[j] = True
    groups = [[names[k] for k in c] for c in _components(n, i, j) if paired[c].any()]
    unpaired = [names[k] for k in range(n) if not paired[k]]
    fit_c = exponent is None
    if fit_c and not np.any(z != 0):
        raise ValueError("fitting the depth exponent needs bearings (z is zero everywhere)")
    if y.size == 0:
        return RangeScaleEstimate(
            names,
            {},
            {},
            float(exponent or 0.0),
            0.0,
            {},
            {},
            {},
            float("nan"),
            0,
            groups,
            unpaired,
        )
    edges = sorted({(int(a), int(b)) for a, b in zip(i, j, strict=True)})
    counts = {(names[a], names[b]): int(np.sum((i == a) & (j == b))) for a, b in edges}

    # Design: columns x_0..x_{n-1} (and c); start from the per-edge medians of y - c0 z.
    design = np.zeros((y.size, n + 1))
    design[np.arange(y.size), i] = 1.0
    design[np.arange(y.size), j] = -1.0
    design[:, n] = z
    c = 0.0 if fit_c else float(exponent)
    start = np.array([np.median((y - c * z)[(i == a) & (j == b)]) for a, b in edges])
    ea = np.array([a for a, _ in edges])
    eb = np.array([b for _, b in edges])
    ew = np.array([counts[(names[a], names[b])] for a, b in edges], dtype=float)
    x = _min_norm(_laplacian(n, ea, eb, ew), _divergence(n, ea, eb, ew * start))
    params = np.append(x, c)
    columns = n + 1 if fit_c else n
    sigma = float("nan")
    cov = np.zeros((columns, columns))
    for _ in range(iterations):
        r = y - design @ params
        sigma = max(_robust_sigma(r), 1e-12)
        w = weight / (1.0 + (r / (threshold * sigma)) ** 2)
        target = y if fit_c else y - c * z
        normal = design[:, :columns].T @ (w[:, None] * design[:, :columns])
        cov = np.linalg.pinv(normal, hermitian=True)
        new = cov @ (design[:, :columns].T @ (w * target))
        step = float(np.max(np.abs(new[:n] - params[:n]))) + (
            abs(float(new[n] - params[n])) if fit_c else 0.0
        )
        params[:columns] = new
        if step < 1e-12:
            break
    r = y - design @ params
    sigma = _robust_sigma(r)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0)) * sigma
    x, c = params[:n], float(params[n])
    medians = {
        (names[a], names[b]): float(np.median((y - c * z)[(i == a) & (j == b)])) for a, b in edges
    }
    return RangeScaleEstimate(
        robots=names,
        scales={names[k]: float(np.exp(x[k])) for k in range(n) if paired[k]},
        log_sigma={names[k]: float(se[k]) for k in range(n) if paired[k]},
        exponent=c,
        exponent_sigma=float(se[n]) if fit_c else 0.0,
        pairs=counts,
        pair_log_ratio={(names[a], names[b]): float(x[a] - x[b]) for a, b in edges},
        pair_median=medians,
        sigma=sigma,
        outliers=int(np.sum(np.abs(r) > 3.0 * sigma)),
        components=groups,
        unpaired=unpaired,
    )


def _robust_sigma(residuals: FloatArray) -> float:
    """Normalised median absolute deviation about the median."""
    if residuals.size == 0:
        return float("nan")
    return robust_sigma(residuals - np.median(residuals))


def _laplacian(n: int, i: IntArray, j: IntArray, w: FloatArray) -> FloatArray:
    """Weighted graph Laplacian of the pairs: ``sum_k w_k (e_i - e_j)(e_i - e_j)^T``."""
    lap = np.zeros((n, n))
    np.add.at(lap, (i, i), w)
    np.add.at(lap, (j, j), w)
    np.add.at(lap, (i, j), -w)
    np.add.at(lap, (j, i), -w)
    return lap


def _divergence(n: int, i: IntArray, j: IntArray, wy: FloatArray) -> FloatArray:
    """Right-hand side ``sum_k w_k y_k (e_i - e_j)``."""
    g = np.zeros(n)
    np.add.at(g, i, wy)
    np.add.at(g, j, -wy)
    return g


def _min_norm(lap: FloatArray, g: FloatArray) -> FloatArray:
    """Minimum-norm solution ``L^+ g``: zero mean in each connected component."""
    return np.linalg.pinv(lap, hermitian=True) @ g


def _components(n: int, i: IntArray, j: IntArray) -> list[IntArray]:
    """Connected components of the graph with edges ``(i_k, j_k)``, in index order."""
    graph = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return [np.flatnonzero(labels == c) for c in range(count)]


@dataclass
class MeetingJackknife:
    """Uncertainty of the scales from whole meetings (:func:`meeting_jackknife`)."""

    meetings: dict[tuple[str, str], int]  # robot pair -> number of meetings
    log_sigma: dict[str, float]  # robot -> jackknife standard error of log s
    exponent_sigma: float  # jackknife standard error of the fitted c (0 when c is given)
    skipped: int = 0  # meetings whose removal left a robot unpaired (not in the sums)


def meetings(stamps: FloatArray, gap: float) -> IntArray:
    """Meeting number of each pair: pairs sorted by stamp start a new meeting after a pause
    longer than ``gap`` seconds."""
    t = np.asarray(stamps, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    starts = np.concatenate([[0], (np.diff(t[order]) > gap).astype(np.int64)])
    out = np.empty(t.size, dtype=np.int64)
    out[order] = np.cumsum(starts)
    return out


def meeting_jackknife(
    robots: Sequence[str],
    pairs: Mapping[tuple[str, str], MutualPairs],
    gap: float = 5.0,
    weight: float = 1.0,
    exponent: float | None = 0.0,
) -> MeetingJackknife:
    """Delete-one-meeting jackknife of :func:`mutual_range_scales` (``weight`` and
    ``exponent`` as there).

    The pairs of one meeting (robot pair, pauses at most ``gap`` s) share geometry, bearings
    and occlusions, so their errors are correlated and the standard errors that treat pairs
    as independent are too small. Leaving each meeting out in turn gives estimates
    ``theta_g``; ``se^2 = (G - 1) / G * sum_g (theta_g - mean theta)^2`` over the ``G``
    meetings. A meeting whose removal leaves a robot unpaired changes the gauge and is left
    out of the sums (counted in ``MeetingJackknife.skipped``)."""
    full = set(mutual_range_scales(robots, pairs, weight=weight, exponent=exponent).scales)
    skipped = 0
    groups = {key: meetings(p.stamps, gap) for key, p in pairs.items()}
    counts = {key: int(g.max() + 1) if g.size else 0 for key, g in groups.items()}
    thetas: list[dict[str, float]] = []
    exponents: list[float] = []
    for key, g in groups.items():
        for m in range(counts[key]):
            keep = g != m
            reduced = dict(pairs)
            p = pairs[key]
            reduced[key] = MutualPairs(p.stamps[keep], p.log_ratio[keep], p.log_cos_ratio[keep])
            result = mutual_range_scales(robots, reduced, weight=weight, exponent=exponent)
            if set(result.scales) != full:
                skipped += 1
                continue
            thetas.append({r: float(np.log(s)) for r, s in result.scales.items()})
            exponents.append(result.exponent)
    sigma: dict[str, float] = {}
    for robot in robots:
        values = np.array([t[robot] for t in thetas if robot in t])
        if values.size > 1:
            sigma[robot] = float(
                np.sqrt((values.size - 1) / values.size * np.sum((values - values.mean()) ** 2))
            )
    c = np.array(exponents)
    c_sigma = (
        float(np.sqrt((c.size - 1) / c.size * np.sum((c - c.mean()) ** 2))) if c.size > 1 else 0.0
    )
    return MeetingJackknife({k: v for k, v in counts.items() if v}, sigma, c_sigma, skipped)


@dataclass
class MapScale:
    """One robot's ranges against a reference map (:func:`map_range_scales`)."""

    scale: float  # measured / map range, whole run (geometric mean 1 over the robots)
    first_half: float  # same gauge, first half of the run
    second_half: float
    observations: int  # landmark observations of labels the map names
    log_spread: float  # robust spread of log(measured / predicted range)


def reference_from_joined_map(
    robots: Sequence[str],
    features: Sequence[tuple[Sequence[str], Sequence[float]]],
    min_members: int = 2,
) -> GroundTruth:
    """A joined map as the landmark reference of :func:`map_range_scales`: ``features`` are
    ``(members, xy)`` with members ``"robot/label"`` (the robots' own labels that C-SAM
    associated into one landmark). Only landmarks seen by at least ``min_members`` robots
    are kept (only they compare robots)."""
    names = set(robots)
    kept = [(m, xy) for m, xy in features if len(m) >= min_members]
    labels: dict[str, dict[int, int]] = {name: {} for name in robots}
    for k, (members, _) in enumerate(kept):
        for member in members:
            robot, _, label = str(member).rpartition("/")
            if robot in names:
                labels[robot][int(label)] = k
    return GroundTruth(
        feature_ids=np.arange(len(kept), dtype=np.int64),
        feature_positions=np.array([xy for _, xy in kept], dtype=float).reshape(-1, 2),
        label_to_feature=labels,
    )


def map_range_scales(
    log: MultiRobotLog,
    reference: GroundTruth,
    noise: NoiseModel,
    exponent: float = 0.0,
) -> dict[str, MapScale]:
    """Each camera's range scale against a common landmark map, relative to the others.

    Every robot is localised against ``reference`` (landmarks held fixed, odometry between
    its feature stamps; :func:`csam_ros.core.truth.localisation.localise`) using its landmark
    observations whose labels the map names, ranges divided by ``cos(bearing)^exponent``;
    its scale is the weighted fit of measured on predicted range
    (:func:`csam_ros.core.truth.calibration.range_scale`). A map that no truth fixed has its own
    scale ``m`` (for C-SAM's joined map: a blend of the cameras' scales), so each fit is
    ``s_i / m``: the scales are returned with geometric mean 1, like
    :func:`mutual_range_scales`. A robot that sees no map landmark in frames of >= 3
    landmarks is left out.
    """
    raw: dict[str, tuple[tuple[float, float, float], int, float]] = {}
    for name, robot in sorted(log.robots.items()):
        labels = reference.label_to_feature.get(name, {})
        f = robot.features
        keep = np.array([int(k) in labels for k in f.labels], dtype=bool)
        if not keep.any():
            continue
        ranges = f.ranges / np.cos(f.bearings) ** exponent
        features = FeatureLog(
            f.stamps[keep],
            f.labels[keep],
            ranges[keep],
            f.bearings[keep],
            f.sigma_range[keep],
            f.sigma_bearing[keep],
        )
        own = replace(robot, features=features)
        snapshots = snapshot_localisation(own, reference, noise)
        if snapshots.stamps.size == 0:
            continue
        loc = localise(own, reference, noise, snapshots)
        predicted = loc.ranges - loc.range_residuals
        raw[name] = (
            range_scale(loc),
            int(keep.sum()),
            robust_sigma(np.log(loc.ranges / predicted)),
        )
    if not raw:
        return {}
    mean = float(np.exp(np.mean([np.log(v[0][0]) for v in raw.values()])))
    return {
        name: MapScale(s / mean, a / mean, b / mean, n, spread)
        for name, ((s, a, b), n, spread) in raw.items()
    }

"""Sub-pixel straight edges: edge points from step fits across short strips, then a robust
total-least-squares line through them.

Edge points. Along a predicted edge, each strip (a short stretch of it, a band a few pixels
across) is fitted with a step I = b + (a − b)·Φ((d − δ)/s) of the signed distance d from the
predicted line, on the raw pixels: δ is the strip's sub-pixel edge offset (maximum likelihood
under Gaussian noise), with variance σ²/Σ(∂I/∂δ)². Grey levels a, b are shared by the whole
edge. A coarse search of one common offset for all strips first absorbs a prior that is off by
a few pixels — or, for a prior uncertain by more, of a line through the strips' own coarse
offsets (a prior tilted against the edge) — and the strips are then fitted coarse to fine (s
from 1.2 px down to 0.45 px) within a pixel or two of that start. Last, the inlying strips'
pixels fit one line together, and every strip's offset moves with it: a strip's own estimate,
from a few dozen pixels, carries a small-sample bias that one line fitted to all of them does
not (``_onto_joint_line``).

Clipping. A sensor clips its noise at black and white, so the mean of a pixel near either end
is not its intensity (lifted near 0, lowered near 1). A step against black (the face's outline
against space) then looks steeper on its bright side and a least-squares step fit puts it
there: measured 0.07–0.1 px inward at low noise on the outline, a range bias of +3 mm at 3 m
for the line system. Given the noise σ, the fit maximises the clipped-Gaussian (Tobit)
likelihood instead: a pixel at black or white says only that intensity plus noise fell beyond
the clip (``estimators.clipped_noise.clipped_likelihood_terms``); Newton steps on that likelihood.

Line. Weighted total least squares (the principal axis of the points, weights 1/σ²) with
iteratively reweighted Tukey biweights so that strips on clutter do not pull the line
(P. J. Huber, "Robust Statistics", 1981; Tukey's biweight with c = 4.685).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estimators.clipped_noise import clipped_moment, clipped_terms, edge_coverage, normal_cdf
from estimators.compiled import compiled, compiled_inline
from estimators.point_fit import EDGE_WIDTH_PX
from estimators.small_linalg import solve_small


@dataclass(frozen=True, slots=True, eq=False)
class EdgePoints:
    """Edge points (K,2 px, image coordinates) with their standard deviation across the edge
    (K,), a usable flag (K,), and the edge's grey levels on the normal's side (``inside``) and
    the other (``outside``)."""

    uv: np.ndarray
    sigma_px: np.ndarray
    ok: np.ndarray
    inside: float
    outside: float
    contrast_sigma: float
    noise_sigma: float

    @property
    def contrast(self) -> float:
        return self.inside - self.outside

    @property
    def contrast_snr(self) -> float:
        return self.contrast / max(self.contrast_sigma, 1e-12)


def _no_points(k: int) -> EdgePoints:
    return EdgePoints(
        np.full((k, 2), np.nan), np.full(k, np.inf), np.zeros(k, bool), 0.0, 0.0, np.inf, np.nan
    )


@compiled_inline
def _profile_at(d: float, delta: float, wall: float, s: float):
    """Basis (3) of a step edge at ``delta`` with a wall ``wall`` px wide showing outside it
    (on the side the normals point away from), at offset ``d`` across the edge: inside
    Φ((d − δ)/s), outside 1 − Φ((d − δ + w)/s) and the wall between them; and their
    derivatives in δ (3). Levels · basis = intensity."""
    f1, p1 = edge_coverage((d - delta) / s, s)
    if wall == 0.0:  # no wall: the outside starts where the inside ends
        f2, p2 = f1, p1
    else:
        f2, p2 = edge_coverage((d - delta + wall) / s, s)
    return f1, 1.0 - f2, f2 - f1, -p1, p2, p1 - p2


@compiled
def _profile_levels(values, d, delta, wall, s, levels, sigma):
    """Grey levels (inside, outside, wall) of values ≈ basis · levels at edge offsets ``delta``
    (per pixel): linear least squares, or scoring steps on the clipped likelihood from
    ``levels`` given the noise σ. The wall's level: with σ, a prior N((inside + outside)/2,
    (|inside − outside|/2)²) — a wall narrower than a pixel barely shows its own grey, and a
    free one would trade with the edge's place at high noise; without σ, a weak tie to the
    outside's (it decides only where no wall shows)."""
    n = len(values)
    levels = levels.copy()
    tie = 1e-3 * n
    basis = np.empty((n, 3))  # fixed while the levels change: computed once
    for i in range(n):
        basis[i, 0], basis[i, 1], basis[i, 2], _, _, _ = _profile_at(d[i], delta[i], wall[i], s)
    tie_vector = np.empty(3)
    start = np.zeros(3)
    for _ in range(8 if sigma > 0 else 1):
        if sigma > 0:
            start = levels.copy()
            spread = max(abs(start[0] - start[1]) / 2.0, 1e-3)
            tie_vector[0], tie_vector[1], tie_vector[2] = -0.5 / spread, -0.5 / spread, 1 / spread
        else:
            root = math.sqrt(tie)
            tie_vector[0], tie_vector[1], tie_vector[2] = 0.0, -root, root
        H = np.outer(tie_vector, tie_vector) + 1e-12 * np.eye(3)
        g = -tie_vector * (tie_vector @ start)
        for i in range(n):
            row = basis[i]
            if sigma > 0:
                intensity = row[0] * levels[0] + row[1] * levels[1] + row[2] * levels[2]
                score, info = clipped_terms(values[i], intensity, sigma)
            else:
                score, info = values[i], 1.0
            for r in range(3):
                g[r] += row[r] * score
                for c in range(3):
                    H[r, c] += info * row[r] * row[c]
        step = solve_small(H, g)
        if not np.all(np.isfinite(step)):
            return np.full(3, np.nan)
        levels = start + step
        if np.sum(np.abs(levels - start)) < 1e-4 and sigma > 0:
            break
    return levels


@compiled
def _two_levels(s11, s12, s22, t1, t2, vv):
    """The least-squares grey levels a, b of v ≈ a·step + b·(1 − step) from the sums
    Σstep², Σstep·other, Σother², Σstep·v, Σother·v, and the cost Σ(v − a·step − b·other)²
    given Σv² = ``vv`` (cost inf when the two columns are degenerate)."""
    det = s11 * s22 - s12 * s12
    if abs(det) < 1e-9 * max(s11 * s22, 1e-12):
        return np.inf, np.nan, np.nan
    a, b = (s22 * t1 - s12 * t2) / det, (s11 * t2 - s12 * t1) / det
    # Σ(v − a·step − b·other)², expanded: the sums already hold it.
    cost = vv - 2.0 * (a * t1 + b * t2)
    cost += a * a * s11 + 2.0 * a * b * s12 + b * b * s22
    return cost, a, b


@compiled
def _step_cost(values, d, strip, base):
    """Least-squares cost of the best two-level step (blur 1.2 px) at offsets ``base[strip]``
    across the band, and its grey levels (cost inf when no step fits)."""
    n = len(values)
    s11 = s12 = s22 = t1 = t2 = vv = 0.0
    for i in range(n):
        step = normal_cdf((d[i] - base[strip[i]]) / 1.2)
        other = 1.0 - step
        s11 += step * step
        s12 += step * other
        s22 += other * other
        t1 += step * values[i]
        t2 += other * values[i]
        vv += values[i] * values[i]
    if n < 3:
        return np.inf, np.nan, np.nan
    return _two_levels(s11, s12, s22, t1, t2, vv)


@compiled
def _tilted_start(values, d, strip, k, grid, max_slope):
    """The prediction's error as a line across the strips (offset of each strip's start,
    K,), when the prediction may be tilted against the edge by up to ``max_slope`` px per
    strip: each strip's own best step offset on ``grid``, then the median of the pairwise
    slopes and of the intercepts (Theil–Sen: H. Theil 1950, P. K. Sen 1968), robust to strips
    that found clutter."""
    m = len(grid)
    sums = np.zeros((k, m, 5))
    for g in range(m):
        for i in range(len(values)):
            step = normal_cdf((d[i] - grid[g]) / 1.2)
            other = 1.0 - step
            row = sums[strip[i], g]
            row[0] += step * step
            row[1] += step * other
            row[2] += other * other
            row[3] += step * values[i]
            row[4] += other * values[i]
    place, found = np.empty(k), np.empty(k)
    count = 0
    for j in range(k):
        best, at = np.inf, np.nan
        for g in range(m):
            s11, s12, s22, t1, t2 = sums[j, g]
            # The strip's own cost up to its Σv² (the same for every offset).
            cost, _, _ = _two_levels(s11, s12, s22, t1, t2, 0.0)
            if cost < best:
                best, at = cost, grid[g]
        if math.isfinite(at):
            place[count], found[count] = j, at
            count += 1
    if count < 3:
        return np.full(k, np.nan)
    slope = min(max(_median_slope(place[:count], found[:count]), -max_slope), max_slope)
    intercept = np.median(found[:count] - slope * place[:count])
    return intercept + slope * np.arange(k)


@compiled
def _median_slope(x, y):
    """Theil–Sen's slope of y over x: the median of the slopes between every two points at
    different x (NaN when there are none)."""
    slopes = []
    for p in range(len(x)):
        for q in range(p + 1, len(x)):
            if abs(x[q] - x[p]) > 1e-9:
                slopes.append((y[q] - y[p]) / (x[q] - x[p]))
    if len(slopes) == 0:
        return np.nan
    return np.median(np.array(slopes))


@compiled
def _fit_offsets(
    values, d, strip, k, grid, half_width, wall_of_strip, noise_sigma, max_slope, place
):
    """Steps 1–3 of ``fit_edge_points`` on a band's pixels (see there): the strips' offsets,
    their standard deviations and usable flags, the grey levels, the contrast's standard
    deviation and the residual noise; ``ok`` all False when no step fits."""
    n = len(values)
    failed = (
        np.zeros(k),
        np.full(k, np.inf),
        np.zeros(k, np.bool_),
        np.nan,
        np.nan,
        np.inf,
        np.nan,
    )
    # 1. Where the strips start: one common offset for the whole edge (a grid search of the
    # step fit on a fixed band) or, when the prediction may be tilted against the edge, the
    # line through the strips' own offsets, if its step fits better.
    best_cost, a, b = np.inf, np.nan, np.nan
    base = np.zeros(k)
    trial = np.empty(k)
    for offset in grid:
        trial[:] = offset
        cost, a_try, b_try = _step_cost(values, d, strip, trial)
        if cost < best_cost:
            best_cost, a, b = cost, a_try, b_try
            base[:] = offset
    if max_slope > 0:
        tilted = _tilted_start(values, d, strip, k, grid, max_slope)
        if np.all(np.isfinite(tilted)):
            cost, a_try, b_try = _step_cost(values, d, strip, tilted)
            if cost < best_cost:
                best_cost, a, b = cost, a_try, b_try
                base[:] = tilted
    if not math.isfinite(a):
        return failed
    near = np.abs(d - base[strip]) <= half_width
    values, d, strip = values[near], d[near], strip[near]
    n = len(values)
    counts = np.bincount(strip, minlength=k)

    # 2. Per-strip offsets within ±max_shift of their start, coarse to fine, with shared
    # grey levels refreshed between scales (a scoring step on the clipped likelihood).
    max_shift = max(1.0, half_width - 1.5)
    delta = base.copy()
    w = wall_of_strip[strip]
    levels = _profile_levels(values, d, delta[strip], w, 1.2, np.array([a, b, b]), noise_sigma)
    if not np.all(np.isfinite(levels)):
        return failed
    jj, jr = np.zeros(k), np.zeros(k)
    for s, count in ((1.2, 2), (0.7, 2), (EDGE_WIDTH_PX, 3)):
        for _ in range(count):
            jj[:] = 0.0
            jr[:] = 0.0
            for i in range(n):
                j = strip[i]
                b0, b1, b2, q0, q1, q2 = _profile_at(d[i], delta[j], w[i], s)
                intensity = b0 * levels[0] + b1 * levels[1] + b2 * levels[2]
                score, info = clipped_terms(values[i], intensity, noise_sigma)
                J = q0 * levels[0] + q1 * levels[1] + q2 * levels[2]  # ∂model/∂δ
                jj[j] += info * J * J
                jr[j] += J * score
            for j in range(k):
                step = min(max(jr[j] / max(jj[j], 1e-12), -0.5), 0.5)
                delta[j] = min(max(delta[j] + step, base[j] - max_shift), base[j] + max_shift)
        levels = _profile_levels(values, d, delta[strip], w, s, levels, noise_sigma)
        if not np.all(np.isfinite(levels)):
            return failed

    # 2b. The strips' offsets moved together onto the line that all their pixels fit best.
    own = delta  # a strip whose own fit ran to its search's end found no edge
    delta = _onto_joint_line(
        values, d, strip, place, delta, w, levels, noise_sigma, base, max_shift
    )

    # 3. Statistics at the solution. Per-pixel information: from the residuals' own variance;
    # with a clipping model, the clipped likelihood's (a clipped pixel tells less than an
    # unclipped one), on the scale of the noise σ scaled by how the residuals compare with what
    # clipped noise leaves (clipping shrinks the residuals' own spread, which would make the
    # points look too precise).
    walled = np.any(wall_of_strip >= 0.05)
    dof = max(n - k - (3 if walled else 2), 1)
    J = np.empty(n)
    weight = np.empty(n)
    rr = excess = spread = 0.0
    aa = ao = oo = 0.0
    for i in range(n):
        b0, b1, b2, q0, q1, q2 = _profile_at(d[i], delta[strip[i]], w[i], EDGE_WIDTH_PX)
        intensity = b0 * levels[0] + b1 * levels[1] + b2 * levels[2]
        r = values[i] - intensity
        rr += r * r
        J[i] = -(q0 * levels[0] + q1 * levels[1] + q2 * levels[2])
        if noise_sigma > 0:
            _, weight[i] = clipped_terms(values[i], intensity, noise_sigma)
            mean, variance, _ = clipped_moment(intensity, noise_sigma)
            excess += (values[i] - mean) ** 2
            spread += variance
        other = b1 + b2
        aa += b0 * b0
        ao += b0 * other
        oo += other * other
    noise2 = rr / dof
    if noise_sigma > 0:
        scale = excess / max(spread, 1e-12) * n / dof
        weight /= max(scale, 0.5)
    else:
        weight[:] = 1.0 / max(noise2, 1e-12)
    info = np.zeros(k)
    for i in range(n):
        info[strip[i]] += weight[i] * J[i] * J[i]
    sigma = 1.0 / np.sqrt(np.maximum(info, 1e-12))
    # Grey-level uncertainty from the linear part: Var(a − b) = σ²·[1 −1](AᵀA)⁻¹[1 −1]ᵀ
    det = aa * oo - ao * ao
    contrast_sigma = np.inf
    if det != 0.0:
        contrast_sigma = math.sqrt(max(noise2 * (oo + aa + 2.0 * ao) / det, 0.0))
    ok = (counts >= 4) & np.isfinite(delta) & (np.abs(own - base) < max_shift - 1e-6)
    ok &= np.isfinite(sigma) & (info > 0)
    return delta, sigma, ok, levels[0], levels[1], contrast_sigma, math.sqrt(noise2)


@compiled
def _onto_joint_line(values, d, strip, place, delta, w, levels, noise_sigma, base, max_shift):
    """The strips' offsets ``delta`` (K,) shifted, all by one line along the edge, onto the line
    δ(x) = α + β·x (x: each strip's place along the edge, px, ``place``) that the pixels of all
    the inlying strips fit best together (maximum likelihood, the grey levels held).

    Each strip's own offset comes from its few dozen pixels, and a maximum-likelihood estimate
    from so few is biased at high noise — by O(σ²/n) (M. H. Quenouille 1956; D. R. Cox and
    E. J. Snell 1968) — where the step is asymmetric: against black, the clipped side. On a
    synthetic step of 0.35 against black under the study's high noise (σ 0.32), the offsets
    and the line through them lay 0.015 px toward the bright side (6000 draws; half that with
    strips twice as long), and the face's outline then shrinks: the line system's range at
    3 m was 0.8 mm long. Two parameters fitted to all the pixels carry a bias the strips'
    count times smaller. Each strip keeps its own scatter about the line (the fits downstream
    judge it); only the line moves.

    Inliers as the line through the edge points will take them (``fit_line_robust``): Tukey's
    biweight on residuals over each strip's σ, scaled by their robust spread, from a
    Theil–Sen start (strips on clutter beside the edge must not tilt the line). With fewer
    than three inliers, or a move over half a pixel, ``delta`` is kept."""
    k = len(delta)
    jj = np.zeros(k)
    n_of = np.zeros(k)
    for i in range(len(values)):
        j = strip[i]
        b0, b1, b2, q0, q1, q2 = _profile_at(d[i], delta[j], w[i], EDGE_WIDTH_PX)
        intensity = b0 * levels[0] + b1 * levels[1] + b2 * levels[2]
        _, info = clipped_terms(values[i], intensity, noise_sigma)
        J = q0 * levels[0] + q1 * levels[1] + q2 * levels[2]
        jj[j] += info * J * J
        n_of[j] += 1.0
    usable = np.flatnonzero((jj > 0) & (n_of >= 4) & (np.abs(delta - base) < max_shift - 1e-6))
    if len(usable) < 3:
        return delta
    x, y, root = place[usable], delta[usable], np.sqrt(jj[usable])
    beta = _median_slope(x, y)
    if not math.isfinite(beta):
        return delta
    alpha = np.median(y - beta * x)
    inlier = np.zeros(len(usable), np.bool_)
    for _ in range(7):
        residual = (y - alpha - beta * x) * root
        spread = max(1.0, 1.4826 * np.median(np.abs(residual)))
        u = residual / (4.685 * spread)
        inlier = np.abs(u) < 1.0
        if np.count_nonzero(inlier) < 3:
            return delta
        weight = np.where(inlier, (1.0 - u * u) ** 2, 0.0) * jj[usable]
        sw, swx, swxx = np.sum(weight), np.sum(weight * x), np.sum(weight * x * x)
        swy, swxy = np.sum(weight * y), np.sum(weight * x * y)
        det = sw * swxx - swx * swx
        if det <= 0.0:
            return delta
        alpha, beta = (swxx * swy - swx * swxy) / det, (sw * swxy - swx * swy) / det
    on_line = np.zeros(k, np.bool_)
    on_line[usable[inlier]] = True
    alpha0, beta0 = alpha, beta
    for _ in range(3):
        h11 = h12 = h22 = g1 = g2 = 0.0
        for i in range(len(values)):
            j = strip[i]
            if not on_line[j]:
                continue
            at = alpha + beta * place[j]
            b0, b1, b2, q0, q1, q2 = _profile_at(d[i], at, w[i], EDGE_WIDTH_PX)
            intensity = b0 * levels[0] + b1 * levels[1] + b2 * levels[2]
            score, info = clipped_terms(values[i], intensity, noise_sigma)
            J = q0 * levels[0] + q1 * levels[1] + q2 * levels[2]
            h11 += info * J * J
            h12 += info * J * J * place[j]
            h22 += info * J * J * place[j] * place[j]
            g1 += J * score
            g2 += J * score * place[j]
        det = h11 * h22 - h12 * h12
        if det <= 0.0:
            return delta
        alpha += min(max((h22 * g1 - h12 * g2) / det, -0.5), 0.5)
        beta += (h11 * g2 - h12 * g1) / det
    shift = (alpha - alpha0) + (beta - beta0) * place
    if not np.all(np.isfinite(shift)) or np.max(np.abs(shift)) > 0.5:
        return delta
    return delta + shift


#: Strips per chunk when collecting a band's pixels: one bounding box per chunk, so that a
#: long slanted edge does not visit the whole rectangle it spans.
_BAND_CHUNK_STRIPS = 8


def _band_pixels(pixels, centers, normals, half_length, reach_across):
    """Pixels near a predicted edge: their values, offsets across the edge from their strip's
    centre along its normal (d), strip index and coordinates — one flat array each (None
    when the band misses the image)."""
    first, last = centers[0], centers[-1]
    chord = last - first
    chord_length = float(np.linalg.norm(chord))
    direction = (
        chord / chord_length if chord_length > 1e-9 else np.array([-normals[0, 1], normals[0, 0]])
    )
    spacing = chord_length / max(len(centers) - 1, 1)
    values, d, strip, coords = _band_kernel(
        pixels, centers, normals, direction, spacing, float(half_length), float(reach_across)
    )
    return None if len(values) == 0 else (values, d, strip, coords)


@compiled
def _band_kernel(pixels, centers, normals, direction, spacing, half_length, reach_across):
    h, w = pixels.shape
    k = len(centers)
    first = centers[0]
    boxes = []
    total = 0
    for i0 in range(0, k, _BAND_CHUNK_STRIPS):
        i1 = min(i0 + _BAND_CHUNK_STRIPS, k) - 1
        # Bounding box of this part of the band (the edge may curve a little: a margin).
        xs = (
            centers[i0, 0] - half_length * direction[0],
            centers[i1, 0] + half_length * direction[0],
        )
        ys = (
            centers[i0, 1] - half_length * direction[1],
            centers[i1, 1] + half_length * direction[1],
        )
        u0 = max(math.floor(min(xs) - reach_across - 2), 0)
        v0 = max(math.floor(min(ys) - reach_across - 2), 0)
        u1 = min(math.ceil(max(xs) + reach_across + 2), w - 1)
        v1 = min(math.ceil(max(ys) + reach_across + 2), h - 1)
        if u1 < u0 or v1 < v0:
            continue
        boxes.append((i0, i1, u0, v0, u1, v1))
        total += (u1 - u0 + 1) * (v1 - v0 + 1)
    values, d_out = np.empty(total), np.empty(total)
    strip_out, coords = np.empty(total, np.int64), np.empty((total, 2))
    m = 0
    for i0, i1, u0, v0, u1, v1 in boxes:
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                t = (u - first[0]) * direction[0] + (v - first[1]) * direction[1]
                j = min(max(round(t / spacing) if spacing > 0 else 0.0, 0.0), k - 1.0)
                j = int(j)
                if j < i0 or j > i1:  # each pixel belongs to one chunk
                    continue
                du, dv = u - centers[j, 0], v - centers[j, 1]
                across = du * normals[j, 0] + dv * normals[j, 1]
                along = -du * normals[j, 1] + dv * normals[j, 0]
                if abs(across) <= reach_across and abs(along) <= half_length:
                    values[m] = pixels[v, u]
                    d_out[m] = across
                    strip_out[m] = j
                    coords[m, 0], coords[m, 1] = u, v
                    m += 1
    return values[:m], d_out[:m], strip_out[:m], coords[:m]


def fit_edge_points(
    pixels: np.ndarray,
    centers_uv: np.ndarray,
    normals: np.ndarray,
    half_length_px: float,
    half_width_px: float,
    *,
    search_px: float = 0.0,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
    noise_sigma: float = 0.0,
    wall_px: np.ndarray | None = None,
    tilt_px: float = 0.0,
) -> EdgePoints:
    """Fit one straight edge in strips.

    ``centers_uv`` (K,2): points on the predicted edge (image px), in order along it;
    ``normals`` (K,2): unit normals there, pointing to the side whose grey level is reported
    as ``inside``. ``half_length_px``: each strip's half length along the edge;
    ``half_width_px``: the band's half width across it. ``search_px``: how far (px) the true
    edge may lie from the prediction; ``tilt_px``: by how much more (px) one end of the
    prediction may be off than the other (a rough hypothesis, tilted against the edge; the
    tilted start is taken when its step fits the band better than any common offset).
    ``keep(coords (P,2)) -> bool (P,)`` may exclude pixels on other features.
    """
    centers = np.asarray(centers_uv, dtype=float).reshape(-1, 2)
    normals = np.asarray(normals, dtype=float).reshape(-1, 2)
    k = len(centers)
    if k < 2:
        return _no_points(k)
    band = _band_pixels(pixels, centers, normals, half_length_px, half_width_px + search_px)
    if band is None:
        return _no_points(k)
    values, d, strip, coords = band
    if keep is not None and len(values):
        inside = keep(coords)
        values, d, strip = values[inside], d[inside], strip[inside]
    if len(values) < 12:
        return _no_points(k)

    grid = np.arange(-search_px, search_px + 1e-9, 1.0) if search_px > 0 else np.zeros(1)
    wall = np.zeros(k) if wall_px is None else np.clip(np.nan_to_num(wall_px), 0.0, 3.0)
    along = np.array([-normals[0, 1], normals[0, 0]])
    place = (centers - centers.mean(axis=0)) @ along  # each strip's place along the edge (px)
    delta, sigma, ok, a, b, contrast_sigma, noise = _fit_offsets(
        values,
        d,
        strip,
        k,
        grid,
        float(half_width_px),
        wall,
        float(noise_sigma),
        tilt_px / (k - 1),
        place,
    )
    if not math.isfinite(a):  # no step fits the band
        return _no_points(k)
    uv = centers + delta[:, None] * normals
    return EdgePoints(uv, sigma, ok, float(a), float(b), contrast_sigma, noise)


def _strip_lattice(pixels, centers, normals, half_length, reach, keep):
    """The pixels under each strip's rectangle, visited on a 1 px lattice in the strip's own
    frame (cheaper than the bounding box of a long, slanted band; a rotated lattice may visit
    a pixel twice or skip one, which an average does not mind): values, offsets across the
    edge (d, from the pixel's centre) and strip index, flat."""
    h, w = pixels.shape
    centers = np.ascontiguousarray(centers, dtype=float)
    normals = np.ascontiguousarray(normals, dtype=float)
    u, v, strip = _lattice_kernel(centers, normals, math.floor(half_length), int(reach), h, w)
    if keep is not None and len(u):
        kept = keep(np.column_stack([u, v]))
        u, v, strip = u[kept], v[kept], strip[kept]
    return _lattice_samples(pixels, centers, normals, u, v, strip)


@compiled
def _lattice_kernel(centers, normals, half_length, reach, h, w):
    """In-image lattice points (u, v, strip), rounded to pixels: strip by strip, across the
    edge from −``reach`` to ``reach``, along it from −``half_length`` to ``half_length``."""
    total = len(centers) * (2 * reach + 1) * (2 * half_length + 1)
    u_out, v_out = np.empty(total), np.empty(total)
    strip_out = np.empty(total, np.int64)
    m = 0
    for k in range(len(centers)):
        cx, cy = centers[k, 0], centers[k, 1]
        nx, ny = normals[k, 0], normals[k, 1]
        tx, ty = -ny, nx
        for i in range(2 * reach + 1):
            c = float(i - reach)
            for j in range(2 * half_length + 1):
                a = float(j - half_length)
                u = np.rint(cx + a * tx + c * nx)
                v = np.rint(cy + a * ty + c * ny)
                if u >= 0 and u <= w - 1 and v >= 0 and v <= h - 1:
                    u_out[m], v_out[m], strip_out[m] = u, v, k
                    m += 1
    return u_out[:m], v_out[:m], strip_out[:m]


@compiled
def _lattice_samples(pixels, centers, normals, u, v, strip):
    """Grey level, offset across the edge from the strip's centre (d) and strip of each
    lattice point."""
    values, d = np.empty(len(u)), np.empty(len(u))
    for m in range(len(u)):
        k = strip[m]
        d[m] = (u[m] - centers[k, 0]) * normals[k, 0] + (v[m] - centers[k, 1]) * normals[k, 1]
        values[m] = pixels[int(v[m]), int(u[m])]
    return values, d, strip


@dataclass(frozen=True, slots=True, eq=False)
class CoarseOffsets:
    """A predicted edge's offset found piece by piece: for each piece (consecutive strips),
    the mean strip index ``place`` (P,), the ``offset`` (P,, px along the normals, whole
    pixels) where its grey-level profile steps, and the step's z-score ``strength`` (P,).
    ``polarity`` +1 when the normals' side is brighter."""

    place: np.ndarray
    offset: np.ndarray
    strength: np.ndarray
    polarity: float


def coarse_edge_offsets(
    pixels: np.ndarray,
    centers_uv: np.ndarray,
    normals: np.ndarray,
    half_length_px: float,
    search_px: float,
    *,
    piece_strips: int = 4,
    side_px: int = 3,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
) -> CoarseOffsets | None:
    """Where a predicted edge really lies, within ±``search_px``, piece by piece — for a
    prediction that may be off by many pixels and, along a long edge, by different amounts.

    Each piece's pixels are averaged into a profile across the edge (1 px bins of the offset
    along the normals); the step is where the mean of ``side_px`` bins on one side differs most
    from the mean of as many on the other (the bin between holds the mixed pixels), with the
    sign both pieces and edge share (the side that is brighter). O(pixels): a cheap first look
    before the step fits of ``fit_edge_points``. None without pixels."""
    centers = np.asarray(centers_uv, dtype=float).reshape(-1, 2)
    normals = np.asarray(normals, dtype=float).reshape(-1, 2)
    k = len(centers)
    if k < 2:
        return None
    reach = math.ceil(search_px) + side_px + 1
    values, d, strip = _strip_lattice(pixels, centers, normals, half_length_px, reach, keep)
    if len(values) < 12:
        return None
    pieces = max(1, round(k / piece_strips))
    place, offset, strength, polarity = _coarse_steps(
        values, d, strip, k, pieces, reach, side_px, math.floor(search_px)
    )
    return CoarseOffsets(place, offset, strength, polarity)


@compiled
def _coarse_steps(values, d, strip, k, pieces, reach, side_px, limit):
    """``coarse_edge_offsets``' profiles and steps, compiled (as NumPy, a few dozen calls on
    arrays of a few hundred bins per edge): each piece's mean strip index, its best step's
    offset (whole pixels within ±``limit``) and z, and the polarity they share."""
    bins = 2 * reach + 1
    total = np.zeros((pieces, bins))
    count = np.zeros((pieces, bins))
    square = np.zeros((pieces, bins))
    strip_sum = np.zeros(pieces)
    strip_count = np.zeros(pieces)
    for m in range(len(values)):
        piece = min((strip[m] * pieces) // k, pieces - 1)
        cell = min(max(int(np.rint(d[m])) + reach, 0), bins - 1)
        total[piece, cell] += values[m]
        count[piece, cell] += 1.0
        square[piece, cell] += values[m] * values[m]
        strip_sum[piece] += strip[m]
        strip_count[piece] += 1.0
    candidates = 2 * limit + 1
    z = np.zeros((pieces, candidates))
    usable = np.zeros((pieces, candidates), np.bool_)
    total_c = np.zeros(bins + 1)
    count_c = np.zeros(bins + 1)
    for q in range(pieces):
        # Window sums by cumulative sums: inside = bins o+1..o+side, outside = o−side..o−1.
        n_all = sum_all = sum_square = 0.0
        for b in range(bins):
            total_c[b + 1] = total_c[b] + total[q, b]
            count_c[b + 1] = count_c[b] + count[q, b]
            n_all += count[q, b]
            sum_all += total[q, b]
            sum_square += square[q, b]
        mean_all = sum_all / max(n_all, 1.0)
        mean_square = sum_square / max(n_all, 1.0)
        # Noise of the pixels around the piece's best step (its spread, edges included: a
        # conservative z).
        spread = math.sqrt(max(mean_square - mean_all * mean_all, 1e-12))
        for i in range(candidates):
            o = i - limit + reach  # bin index of the candidate
            in_sum = total_c[o + side_px + 1] - total_c[o + 1]
            in_n = count_c[o + side_px + 1] - count_c[o + 1]
            out_sum = total_c[o] - total_c[o - side_px]
            out_n = count_c[o] - count_c[o - side_px]
            usable[q, i] = in_n >= 3 and out_n >= 3
            step = in_sum / max(in_n, 1.0) - out_sum / max(out_n, 1.0) if usable[q, i] else 0.0
            noise = spread * math.sqrt(1.0 / max(in_n, 1.0) + 1.0 / max(out_n, 1.0))
            z[q, i] = step / noise
    rise = fall = 0.0
    for q in range(pieces):
        rise += z[q].max()
        fall += (-z[q]).max()
    polarity = 1.0 if rise >= fall else -1.0
    place, offset, strength = np.empty(pieces), np.empty(pieces), np.empty(pieces)
    for q in range(pieces):
        best, best_z = 0, -np.inf
        for i in range(candidates):
            signed = polarity * z[q, i] if usable[q, i] else -np.inf
            if signed > best_z:
                best, best_z = i, signed
        place[q] = strip_sum[q] / max(strip_count[q], 1.0)
        offset[q] = float(best - limit)
        strength[q] = best_z
    return place, offset, strength, polarity


@dataclass(frozen=True, slots=True, eq=False)
class Line2D:
    """A line n·x = c (unit normal n) fitted to points; ``inliers`` flags the points kept,
    ``rms_px`` their RMS distance, ``centroid`` their weighted centroid."""

    normal: np.ndarray
    offset: float
    centroid: np.ndarray
    inliers: np.ndarray
    rms_px: float

    @property
    def direction(self) -> np.ndarray:
        return np.array([-self.normal[1], self.normal[0]])

    def distance(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=float) @ self.normal - self.offset


@compiled
def _weighted_tls(points: np.ndarray, weights: np.ndarray):
    """Weighted total least squares: the line through the weighted centroid along the major
    axis of the weighted scatter (closed form for 2×2: θ = ½·atan2(2sxy, sxx − syy))."""
    total = weights.sum()
    cx = np.sum(weights * points[:, 0]) / total
    cy = np.sum(weights * points[:, 1]) / total
    x, y = points[:, 0] - cx, points[:, 1] - cy
    sxx = np.sum(weights * x * x)
    syy = np.sum(weights * y * y)
    sxy = np.sum(weights * x * y)
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # direction of the major axis
    nx, ny = -math.sin(theta), math.cos(theta)
    return nx, ny, nx * cx + ny * cy, cx, cy


@compiled
def _robust_line(points, sigma, tukey_c, iterations):
    """``fit_line_robust``'s iterations: (normal x, normal y, offset, centroid x, centroid y,
    inlier flags); the flags all False when fewer than 3 points are inliers."""
    base = 1.0 / np.maximum(sigma, 1e-9) ** 2
    nx, ny, offset, cx, cy = _weighted_tls(points, base)
    for _ in range(iterations):
        residual = (points[:, 0] * nx + points[:, 1] * ny - offset) / sigma
        # Scale the threshold by the robust spread so that mis-stated σ does not reject all.
        spread = max(1.0, 1.4826 * np.median(np.abs(residual)))
        u = residual / (tukey_c * spread)
        tukey = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        if tukey.sum() < 3 or np.count_nonzero(tukey) < 3:
            break
        nx, ny, offset, cx, cy = _weighted_tls(points, base * tukey)
    residual = (points[:, 0] * nx + points[:, 1] * ny - offset) / sigma
    spread = max(1.0, 1.4826 * np.median(np.abs(residual)))
    inliers = np.abs(residual) < tukey_c * spread
    return nx, ny, offset, cx, cy, inliers


def fit_line_robust(
    points: np.ndarray, sigma_px: np.ndarray, *, tukey_c: float = 4.685, iterations: int = 6
) -> Line2D | None:
    """Weighted total least squares with Tukey reweighting of normalised residuals; None with
    fewer than 3 points. Points whose normalised residual exceeds ``tukey_c`` are outliers."""
    points = np.ascontiguousarray(points, dtype=float).reshape(-1, 2)
    sigma = np.ascontiguousarray(sigma_px, dtype=float).reshape(-1)
    if len(points) < 3:
        return None
    nx, ny, offset, cx, cy, inliers = _robust_line(points, sigma, tukey_c, iterations)
    if inliers.sum() < 3:
        return None
    normal = np.array([nx, ny])
    rms = float(np.sqrt(np.mean((points[inliers] @ normal - offset) ** 2)))
    return Line2D(normal, float(offset), np.array([cx, cy]), inliers, rms)


def intersect(a: Line2D, b: Line2D) -> np.ndarray | None:
    """The intersection point of two lines, or None when they are (nearly) parallel."""
    M = np.array([a.normal, b.normal])
    if abs(np.linalg.det(M)) < 1e-6:
        return None
    return np.linalg.solve(M, np.array([a.offset, b.offset]))

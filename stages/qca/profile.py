"""Diameter profile, reference diameter and lesions of one vessel.

Reads/writes nothing. :func:`vessel_profile` takes a vessel's arc positions and radii (and the
junctions along it) and returns the profile sampled every ``step_mm`` plus the lesions found on it.

Reference diameter — what the lumen would be without disease. It follows the vessel's taper and drops
at every side branch (Murray's law, r_before³ = r_after³ + r_branch³), so it is fitted, robustly, as

    log r_ref(s) = c0 + c1·s + c2·s² + Σ_j [d_j·H((s − s_j) / 2 mm) + e_j·(s − s_j)₊]

with H the smoothstep 0→1, one step d_j and one change of taper e_j per side branch at s_j (e_j has
a weak ridge prior towards 0: a vessel whose continuation is a different, flatter vessel). Each step is tied (a ridge prior,
weight ``murray_weight`` samples) to what Murray's law predicts from the branch's own proximal radius
and the parent's radius just before it, so a spurious stub of a reconstruction cannot swallow a
lesion, yet a real branch whose measured size is off still gets its step from the data. Junctions
with only a stub (shorter than the tree's ``min_branch_mm``) get a step too, pulled weakly towards
zero: where a trunk ends in a small branch that the tree follows as its continuation, the lumen drops
there without any side branch to predict it. Murray's prediction is capped at :data:`MAX_BRANCH_SHARE` of the
flow (the vessel continues into its larger child, so a side branch takes at most half), and a step is fitted
only where the profile measures the lumen on both sides of it (a chain of branches within a few mm of the
vessel's start would otherwise be set by the prior alone and lift the reference far above the lumen). The fit is
iteratively reweighted: ten Huber rounds (which never drop a point, so the start is close to the L1
fit and not dragged by a lesion) then Tukey biweight on the residuals, with a tighter cut below the fit than above
it: lesions lie below the reference, never above), over the whole vessel except 1 mm before to 3 mm
after each junction (where the lumen widens into the branch). The robust scale is floored at 1 % of
the radius so an exact profile gives an exact reference.

Lesions — the relative narrowing δ(s) = 1 − d(s)/d_ref(s) is searched for its deepest point; if that
reaches ``min_ds`` (default 20 %) it is a lesion: MLD = the profile's diameter there, reference = d_ref
there, %DS = 100·δ, position = its arc length from the vessel's origin. Its **length** is twice the
full width at half of that maximal narrowing (2 × FWHM): for the symmetric raised-cosine narrowing of
the synthetic engine that is exactly the obstruction length (the distance between the points where the
lumen leaves and rejoins the reference), and unlike the departure points themselves it does not
depend on how noise hides the shallow shoulders. ``fwhm_mm`` is reported too. The lesion's
full extent (peak ± FWHM) is then removed and the search repeats.

Profile smoothing: a Gaussian of ``smooth_mm`` (σ) over the resampled radii; 0 keeps an exact profile
exact. Reconstructions use ~1 mm (their radii are fitted on 0.5 mm voxels; see docs/QCA.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Profile", "vessel_profile", "reference_fit"]

JUNCTION_BEFORE_MM = 1.0
JUNCTION_AFTER_MM = 3.0
STEP_WIDTH_MM = 2.0
MAX_BRANCH_SHARE = 0.5  # a side branch carries at most half the flow (r³) before it: the vessel continues into the larger child
HUBER_ITERATIONS = 10


@dataclass
class Profile:
    s: np.ndarray  # mm from the vessel origin
    diameter: np.ndarray  # mm (smoothed)
    reference: np.ndarray  # mm
    valid: np.ndarray  # bool: samples where lesions are searched
    lesions: list = field(default_factory=list)  # dicts


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _identifiable_steps(s, fitted, steps, min_support: int):
    """The steps (s_j, r_branch), sorted by s_j, that the profile can measure: at least ``min_support``
    fitted samples between the step and its neighbours on both sides. A step with no data before it
    (several branches leaving within a few mm of the vessel's start) would be set by its Murray prior
    alone, and a chain of such steps lifts the reference there far above the lumen; without the step the
    level before it is the level after it."""
    kept = []
    for i, (sj, rb) in enumerate(steps):
        lo = kept[-1][0] if kept else -np.inf
        hi = steps[i + 1][0] if i + 1 < len(steps) else np.inf
        if np.count_nonzero(fitted & (s > lo) & (s < sj)) >= min_support and \
                np.count_nonzero(fitted & (s > sj) & (s < hi)) >= min_support:
            kept.append((sj, rb))
    return kept


def reference_fit(s, r, junctions=(), fit_mask=None, murray_weight: float = 20.0, iterations: int = 20,
                  scale_floor: float = 0.01, spurs=(), spur_weight: float = 2.0, hinge_weight: float = 0.05,
                  min_support_mm: float = 2.0):
    """Robust reference radius at ``s`` (see the module docstring). ``junctions``: [(s_j, r_branch)].
    A side branch's step is fitted only where ``min_support_mm`` of fitted samples measure the lumen on both
    sides of it (:func:`_identifiable_steps`)."""
    s = np.asarray(s, float)
    r = np.maximum(np.asarray(r, float), 1e-3)
    y = np.log(r)
    n = len(s)
    L = max(float(s[-1] - s[0]), 1.0) if n else 1.0
    x = (s - s[0]) / L
    cols = [np.ones(n), x, x * x]
    prior_rows, prior_vals = [], []
    base = np.ones(n, bool) if fit_mask is None else np.asarray(fit_mask, bool).copy()
    prior_w = []
    steps = sorted(((float(sj), rb) for sj, rb in list(junctions) + [(sp, None) for sp in spurs]
                    if s[0] + 0.5 < sj < s[-1] - 0.5), key=lambda j: j[0])
    for sj, _ in steps:
        base &= ~((s > sj - JUNCTION_BEFORE_MM) & (s < sj + JUNCTION_AFTER_MM))
    spacing = float(np.median(np.diff(s))) if n > 1 else 1.0
    for sj, rb in _identifiable_steps(s, base, steps, max(1, int(round(min_support_mm / max(spacing, 1e-6))))):
        cols.append(_smoothstep((s - sj) / STEP_WIDTH_MM))
        prior_rows.append(len(cols) - 1)
        if rb is None:  # a stub: no Murray prediction, a weak pull towards no step
            prior_vals.append(0.0)
            prior_w.append(spur_weight)
        else:
            before = (s >= sj - 4.0) & (s <= sj - JUNCTION_BEFORE_MM)
            r_before = float(np.median(r[before])) if before.any() else float(np.interp(sj, s, r))
            ratio3 = min((float(rb) / max(r_before, 1e-3)) ** 3, MAX_BRANCH_SHARE)
            prior_vals.append(np.log1p(-ratio3) / 3.0)
            prior_w.append(murray_weight)
        cols.append(np.maximum(s - sj, 0.0) / L)  # the taper may change at a branch point too
        prior_rows.append(len(cols) - 1)
        prior_vals.append(0.0)
        prior_w.append(hinge_weight)
    if base.sum() < 4:  # a short vessel that is all junction: fit what there is
        base = np.ones(n, bool)
    X = np.stack(cols, 1)
    k = X.shape[1]
    lam = np.sqrt(np.asarray(prior_w, float))
    P = np.zeros((len(prior_rows), k))
    for i, c in enumerate(prior_rows):
        P[i, c] = lam[i]
    pv = lam * np.asarray(prior_vals, float)
    if base.sum() < 8 or L < 3.0:
        X, P = X[:, :1], np.zeros((0, 1))
        pv = np.zeros(0)
    w = base.astype(float)
    beta = None
    k = X.shape[1]
    phase_end = [HUBER_ITERATIONS, iterations]  # Huber rounds, then Tukey rounds; each phase stops once stable
    it = 0
    for phase, last in enumerate(phase_end):
        while it < last:
            it += 1
            sw = np.sqrt(w)
            # a tiny ridge keeps the solve defined when the weights leave a column without support
            A = np.concatenate([X * sw[:, None], P, 1e-6 * np.eye(k)])
            b = np.concatenate([y * sw, pv, np.zeros(k)])
            beta = np.linalg.lstsq(A, b, rcond=None)[0]
            e = y - X @ beta
            sel = base & (w > 0)
            med = np.median(e[sel]) if sel.any() else 0.0
            scale = max(1.4826 * float(np.median(np.abs(e[base] - med))) if base.any() else 0.0, scale_floor)
            w_old = w
            if phase == 0:  # start near the L1 fit: Huber never drops a point
                w = np.minimum(1.0, 1.345 * scale / np.maximum(np.abs(e - med), 1e-12)) * base
            else:
                c_hi, c_lo = 4.685 * scale, 2.5 * scale
                u = np.where(e >= 0, e / c_hi, e / c_lo)
                w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0) * base
            if w.sum() < 4:
                w = base.astype(float)
            if np.max(np.abs(w - w_old)) < 1e-3:
                break
        it = max(it, last) if phase == 0 else it
    return np.exp(X @ beta)


def vessel_profile(s_nodes, r_nodes, junctions=(), *, spurs=(), step_mm: float = 0.25, smooth_mm: float = 0.0,
                   min_ds: float = 20.0, skip_start_mm: float = 0.0, skip_end_mm: float = 0.0,
                   murray_weight: float = 20.0) -> Profile:
    """Profile and lesions of one vessel (module docstring). ``junctions``: [(s_j, r_branch)];
    ``skip_start_mm``/``skip_end_mm``: ends where no lesion is searched (a side branch's first mm carry
    its parent's lumen; a reconstruction's free ends are unreliable)."""
    s_nodes = np.asarray(s_nodes, float)
    r_nodes = np.asarray(r_nodes, float)
    L = float(s_nodes[-1]) if len(s_nodes) else 0.0
    n = max(int(round(L / step_mm)), 1) + 1
    s = np.linspace(0.0, L, n)
    r = np.interp(s, s_nodes, r_nodes)
    if smooth_mm > 0 and n > 3:
        from scipy.ndimage import gaussian_filter1d

        r = gaussian_filter1d(r, smooth_mm / (L / (n - 1)), mode="nearest")
    fit_mask = s >= skip_start_mm  # a side branch's first mm measure its parent's lumen
    ref = reference_fit(s, r, junctions, fit_mask, murray_weight=murray_weight, spurs=spurs)
    valid = (s >= skip_start_mm) & (s <= L - skip_end_mm)
    prof = Profile(s, 2 * r, 2 * ref, valid)
    prof.lesions = find_lesions(s, r, ref, valid, min_ds=min_ds)
    return prof


def _crossing(s, d, k, half, step):
    """Arc position where δ falls below ``half`` walking from sample k by ``step`` (±1), interpolated, and whether
    it does so before the profile's end (if not: the end)."""
    j = k
    while 0 <= j + step < len(d) and d[j + step] > half:
        j += step
    if not (0 <= j + step < len(d)):
        return float(s[j]), False
    a, b = d[j], d[j + step]  # a > half ≥ b
    t = (a - half) / max(a - b, 1e-12)
    return float(s[j] + t * (s[j + step] - s[j])), True


def find_lesions(s, r, ref, valid, min_ds: float = 20.0, max_lesions: int = 8) -> list[dict]:
    """Lesions of a profile (radius ``r`` and reference ``ref`` at ``s``), deepest first.

    A narrowing that reaches the vessel's distal end (the lumen never comes back to half its depth) is the
    vessel tapering out, where its masks fade, not a stenosis: there is no distal lumen to grade it against."""
    delta = 1.0 - np.asarray(r, float) / np.maximum(np.asarray(ref, float), 1e-6)
    work = np.where(valid, delta, -np.inf)
    out = []
    while len(out) < max_lesions and len(work):
        k = int(np.argmax(work))
        peak = float(work[k])
        if not np.isfinite(peak) or 100 * peak < min_ds:
            break
        half = peak / 2
        left, _ = _crossing(s, delta, k, half, -1)
        right, recovers = _crossing(s, delta, k, half, +1)
        fwhm = right - left
        if not recovers:
            work[s >= left - fwhm / 2] = -np.inf
            continue
        out.append({"position_mm": float(s[k]), "mld_mm": float(2 * r[k]), "reference_mm": float(2 * ref[k]),
                    "ds_percent": 100.0 * peak, "length_mm": 2.0 * fwhm, "fwhm_mm": fwhm,
                    "start_mm": max(float(s[k]) - fwhm, float(s[0])), "end_mm": min(float(s[k]) + fwhm, float(s[-1]))})
        work[(s >= left - fwhm / 2) & (s <= right + fwhm / 2)] = -np.inf
    return out

"""Procedural coronary anatomy: seeded left and right coronary trees on a heart-shaped surface.

Reads nothing; :func:`generate` builds a :class:`CoronaryAnatomy` from a seed, and
:meth:`CoronaryAnatomy.label_volume` turns it into a CTA-like label volume (uint8, 1 = left tree,
2 = right tree, with its index→world affine), which ``prep-ct`` then prepares exactly like a real
CTA segmentation. The analytic ground truth (centreline polylines with radius, stenosis list) is kept
on the trees for tests and acceptance figures.

World frame: DICOM LPS in mm (+x patient left, +y posterior, +z superior), heart centre near the
isocentre (origin). The heart is a half-ellipsoid (the ventricles) whose base plane carries the
atrioventricular (AV) grooves and whose long axis runs from the base (posterior, superior, right)
towards the apex (anterior, inferior, left), with random size, orientation and short-axis
eccentricity. Surface coordinates of a point: meridian angle ``phi`` (0 at the base ring, π/2 at the
apex, beyond π/2 on the far side of the apex, negative above the base) and azimuth ``theta`` in the
short-axis plane (0 = the heart's anterior direction, 90° = the patient's left projected onto the
short-axis plane). The
anterior interventricular groove sits at ``theta_lad`` ≈ −5…12°, the posterior one (crux) 180° away.

Anatomy (lengths are arc lengths of the centreline, radii r = Ø/2):

* Left tree: left main (5–15 mm, Ø 4–5 mm) from the aortic root to the AV groove, splitting into the
  LAD (anterior interventricular groove to and around the apex, 100–140 mm, Ø 3–4 mm proximal) with
  1–3 diagonals and 2–4 septal twigs, and the LCx (left AV groove, 60–90 mm; it reaches the crux in
  left-dominant hearts) with 1–3 obtuse marginals; optional ramus intermedius (trifurcation).
* Right tree: RCA (100–140 mm, Ø 3.5–4.5 mm) from the aortic root along the right AV groove, with a
  conus branch, 1–3 acute marginals and, by dominance (right 80 %, co-dominant 10 %, left 10 %), the
  PDA down the posterior interventricular groove and a posterolateral branch (PLB).
* Radii taper along each branch and drop at every side branch so that Murray's law
  r_parent³ = r_after³ + r_child³ holds at the branch point (the drop is smoothed over 2 mm).
  Smallest lumen Ø ≥ 1.2 mm (Ø ≥ 1 mm inside stenoses).
* Tortuosity: a smooth sum of sinusoids (wavelength 8–30 mm, amplitude ≤ 1.5 mm) sideways on the
  surface. 0–3 stenoses per tree on vessels of Ø ≥ 2 mm: 25–90 % diameter reduction requested,
  3–15 mm long, raised-cosine profile; the applied reduction is capped so the residual lumen keeps
  Ø ≥ 1 mm (a 0.35–0.5 mm CTA mask cannot resolve thinner lumens); both figures are recorded.

Children never start at their parent's distal end except the left-main split, so bifurcations are
unambiguous: the number of bifurcations of a tree is Σ over branch points of (degree − 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

STEP_MM = 0.25  # sampling of the analytic centrelines
R_MIN = 0.6  # smallest radius of a vessel (mm)
R_MIN_STENOSIS = 0.5  # smallest residual radius inside a stenosis (mm)


# ---------------------------------------------------------------------------------------------- heart
@dataclass
class Heart:
    """Half-ellipsoid ventricles: base centre, orthonormal frame (a anterior, c left, u long axis)."""

    base_centre: np.ndarray
    a: np.ndarray
    c: np.ndarray
    u: np.ndarray  # base → apex
    length: float  # base plane to apex, mm
    ra: float  # short-axis semi-axis along a, mm
    rc: float  # along c
    theta_lad: float  # azimuth of the anterior interventricular groove, rad

    @property
    def centre(self) -> np.ndarray:
        """Centre of the ventricular mass (40 % of the way from the base to the apex)."""
        return self.base_centre + 0.4 * self.length * self.u

    def surface(self, phi, theta, h=0.0) -> np.ndarray:
        """World points at surface coordinates (phi, theta), moved h mm along the outward normal."""
        phi, theta, h = np.broadcast_arrays(np.asarray(phi, float), np.asarray(theta, float), np.asarray(h, float))
        p = self.ra * np.cos(phi) * np.cos(theta)
        q = self.rc * np.cos(phi) * np.sin(theta)
        z = self.length * np.sin(phi)
        pts = self.base_centre + p[..., None] * self.a + q[..., None] * self.c + z[..., None] * self.u
        n = (p / self.ra**2)[..., None] * self.a + (q / self.rc**2)[..., None] * self.c + (z / self.length**2)[..., None] * self.u
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return pts + h[..., None] * n

    def normal_at(self, x) -> np.ndarray:
        """Outward normal of the ellipsoid level set through world points x (N×3)."""
        d = np.asarray(x, float) - self.base_centre
        p, q, z = d @ self.a, d @ self.c, d @ self.u
        n = (p / self.ra**2)[:, None] * self.a + (q / self.rc**2)[:, None] * self.c + (z / self.length**2)[:, None] * self.u
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "long_axis": self.u.tolist(), "base_centre": self.base_centre.tolist(),
                "anterior_axis": self.a.tolist(), "left_axis": self.c.tolist(), "length_mm": self.length,
                "radii_mm": [self.ra, self.rc]}


def random_heart(rng: np.random.Generator) -> Heart:
    # long axis: 35–55° left of the sagittal plane (seen from above) and 15–35° below the horizontal
    az = math.radians(rng.uniform(35, 55))
    el = math.radians(rng.uniform(15, 35))
    u = np.array([math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), -math.sin(el)])
    # short-axis frame: c = the patient's left projected onto the short-axis plane (lateral LV wall),
    # a = the in-plane direction orthogonal to it on the anterior side (anterior interventricular groove)
    left = np.array([1.0, 0.0, 0.0])
    c = left - (left @ u) * u
    c /= np.linalg.norm(c)
    a = np.cross(u, c)
    if a[1] > 0:
        a = -a
    roll = math.radians(rng.uniform(-10, 10))  # rotation of the short-axis frame about u
    a, c = math.cos(roll) * a + math.sin(roll) * c, -math.sin(roll) * a + math.cos(roll) * c
    length = rng.uniform(72, 92)
    r = rng.uniform(36, 44)
    ecc = rng.uniform(0.9, 1.1)
    centre = rng.normal(0, 4, 3)
    base = centre - 0.4 * length * u
    return Heart(base, a, c, u, length, r * ecc, r / ecc, math.radians(rng.uniform(-5, 12)))


# ---------------------------------------------------------------------------------------------- branches
@dataclass
class Branch:
    name: str
    parent: int  # index of the parent branch, −1 for a root
    points: np.ndarray  # K×3 world mm, proximal → distal, STEP_MM apart
    radius: np.ndarray  # K mm
    params: np.ndarray  # K×2 (phi, theta) surface coordinates before tortuosity (nan where none)
    attach: int = -1  # index of the parent point the branch starts at

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass
class Tree:
    side: str
    branches: list[Branch] = field(default_factory=list)
    stenoses: list[dict] = field(default_factory=list)

    def index(self, name: str) -> int:
        return [b.name for b in self.branches].index(name)

    def truth(self):
        """The analytic ground truth in the prepared-case layout (:class:`stages.core.prepared_case.CaseTruth`)."""
        from .core.prepared_case import CaseTruth

        pts = np.concatenate([b.points for b in self.branches])
        rad = np.concatenate([b.radius for b in self.branches])
        br = np.concatenate([np.full(len(b.points), i) for i, b in enumerate(self.branches)])
        return CaseTruth(pts, rad, br, [b.parent for b in self.branches], [b.name for b in self.branches])

    def samples(self, step: float = STEP_MM) -> tuple[np.ndarray, np.ndarray]:
        """Centreline points and radii of all branches, resampled at ``step`` mm (for the union of balls)."""
        pts, rad = [], []
        for b in self.branches:
            p, r = resample(b.points, b.radius, step)
            pts.append(p)
            rad.append(r)
        return np.concatenate(pts), np.concatenate(rad)

    def bifurcation_count(self) -> int:
        """Σ (degree − 2) over branch points: a child off a parent's middle adds 1, a split of n children at a
        parent's end adds n − 1."""
        count = 0
        ends: dict[int, int] = {}
        for b in self.branches:
            if b.parent < 0:
                continue
            if b.attach >= len(self.branches[b.parent].points) - 1:
                ends[b.parent] = ends.get(b.parent, 0) + 1
            else:
                count += 1
        return count + sum(n - 1 for n in ends.values())

    def sdf(self, x, step: float = 0.1) -> np.ndarray:
        """Signed distance to the tube surface (negative inside), as min over balls |x − c| − r."""
        from scipy.spatial import cKDTree

        pts, rad = self.samples(step)
        x = np.asarray(x, float).reshape(-1, 3)
        tree = cKDTree(pts)
        rmax = float(rad.max())
        # the minimising ball is within (nearest distance + rmax − rmin) of x: query enough neighbours
        d0, _ = tree.query(x)
        out = np.full(len(x), np.inf)
        k = 64
        dd, ii = tree.query(x, k=k)
        vals = dd - rad[np.minimum(ii, len(rad) - 1)]
        vals[~np.isfinite(dd)] = np.inf
        out = vals.min(axis=1)
        # rare points where k neighbours did not reach far enough: exact ball query
        bad = np.nonzero(dd[:, -1] < d0 + rmax)[0]
        for i in bad:
            idx = tree.query_ball_point(x[i], d0[i] + rmax)
            out[i] = np.min(np.linalg.norm(pts[idx] - x[i], axis=1) - rad[idx])
        return out


def resample(points, radius, step: float, params=None):
    """Resample a polyline (and its radius / params) at uniform arc-length ``step``; keeps both ends."""
    points = np.asarray(points, float)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(round(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    out = np.stack([np.interp(t, s, points[:, k]) for k in range(3)], axis=1)
    r = np.interp(t, s, radius)
    if params is None:
        return out, r
    pr = np.stack([np.interp(t, s, params[:, k]) for k in range(params.shape[1])], axis=1)
    return out, r, pr


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _arclength(points):
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


class _Builder:
    """Builds the branches of one tree on a heart: geometry first, radii after all children are known."""

    def __init__(self, heart: Heart, rng: np.random.Generator, side: str):
        self.heart, self.rng, self.side = heart, rng, side
        self.tree = Tree(side)
        self.r0: dict[int, float] = {}  # nominal start radius per branch
        self.taper: dict[int, float] = {}

    # geometry --------------------------------------------------------------------------
    def _finish(self, pts, params, length, start=None, tort=1.0):
        """Resample, add tortuosity (zero at the start), cut at ``length`` and glue the start to ``start``."""
        pts, _, params = resample(pts, np.zeros(len(pts)), STEP_MM / 2, params)
        s = _arclength(pts)
        tangent = np.gradient(pts, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        side = np.cross(tangent, self.heart.normal_at(pts))
        side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
        w = np.zeros(len(pts))
        for _ in range(3):
            lam = self.rng.uniform(8, 30)
            amp = self.rng.uniform(0.2, 0.6) * tort * min(1.0, lam / 15)
            w += amp * np.sin(2 * np.pi * s / lam + self.rng.uniform(0, 2 * np.pi))
        w -= w[0]
        w *= _smoothstep(s / 8.0)  # children leave their parent smoothly
        pts = pts + w[:, None] * side
        if start is not None:
            # move the branch onto its parent's actual (tortuous) centre; the shift fades over 40 mm so
            # the branch still leaves at its designed angle instead of hugging the parent (which would
            # leave a sub-voxel gap between the two lumens: a loop in any skeleton)
            delta = np.asarray(start, float) - pts[0]
            pts = pts + (1 - _smoothstep(s / 40.0))[:, None] * delta
        s = _arclength(pts)
        keep = s <= length
        keep[: max(2, int(np.count_nonzero(keep)))] = True
        pts, params = pts[keep], params[keep]
        pts, _, params = resample(pts, np.zeros(len(pts)), STEP_MM, params)
        return pts, params

    def add(self, name, parent, pts, params, attach=-1, r0=1.0, taper=0.2) -> int:
        b = Branch(name, parent, pts, np.zeros(len(pts)), params, attach)
        self.tree.branches.append(b)
        i = len(self.tree.branches) - 1
        self.r0[i], self.taper[i] = r0, taper
        return i

    def surface_branch(self, name, parent, attach, phi, theta, h_extra, length, r0, taper=0.2, tort=1.0):
        """A branch following surface coordinates (phi(t), theta(t)) sampled densely, riding r + gap above."""
        h = r0 + 0.3 + np.asarray(h_extra, float)
        pts = self.heart.surface(phi, theta, h)
        params = np.stack(np.broadcast_arrays(np.asarray(phi, float), np.asarray(theta, float)), axis=1)
        start = self.tree.branches[parent].points[attach] if parent >= 0 else None
        pts, params = self._finish(pts, params, length, start, tort)
        pts, params = self._keep_clear(pts, params, r0)
        if len(pts) < 2 or _arclength(pts)[-1] < min(8.0, 0.6 * length):
            return -1  # would run into another vessel almost at once: no such branch
        return self.add(name, parent, pts, params, attach, r0, taper)

    def _keep_clear(self, pts, params, r0, clearance: float = 1.5):
        """Cut a new branch 3 mm before it comes within ``clearance`` (wall to wall) of an existing vessel.

        Vessels that touch would fuse in the label volume (a loop in the skeleton, a false bifurcation).
        Near its own origin (10 mm) a branch is of course allowed to touch its parent and siblings.
        """
        from scipy.spatial import cKDTree

        if not self.tree.branches:
            return pts, params
        others = np.concatenate([b.points for b in self.tree.branches])
        r_oth = np.concatenate([np.full(len(b.points), self.r0[i]) for i, b in enumerate(self.tree.branches)])
        far = np.linalg.norm(others - pts[0], axis=1) > 10.0
        others, r_oth = others[far], r_oth[far]
        if len(others) == 0:
            return pts, params
        d, j = cKDTree(others).query(pts)
        gap = d - r0 - r_oth[j]
        s = _arclength(pts)
        bad = np.nonzero((gap < clearance) & (s > 6.0))[0]
        if len(bad) == 0:
            return pts, params
        cut = int(np.searchsorted(s, s[bad[0]] - 3.0))
        return pts[:cut], params[:cut]

    def attach_point(self, parent: int, at_mm: float) -> int:
        b = self.tree.branches[parent]
        s = _arclength(b.points)
        return int(np.clip(np.searchsorted(s, at_mm), 1, len(s) - 2))

    # radii -----------------------------------------------------------------------------
    def assign_radii(self):
        """Taper × Murray drops at children; a child starts at its nominal radius × the parent's taper there.

        Murray holds exactly at every branch point: the parent's r³ (before taper) drops by the child's
        (r_child / taper)³. A side branch the parent cannot feed (its remainder would fall below the
        smallest radius) is removed rather than clamped, so no branch point breaks the law.
        """
        br = self.tree.branches
        drop: set[int] = set()
        for i, b in enumerate(br):  # parents precede children in the list
            if i in drop:
                continue
            s = _arclength(b.points)
            total = s[-1] if s[-1] > 0 else 1.0
            tau = 1.0 - self.taper[i] * s / total
            kids = sorted((j for j, c in enumerate(br) if c.parent == i and c.attach < len(s) - 1),
                          key=lambda j: br[j].attach)
            cube = np.full(len(s), self.r0[i] ** 3)
            remaining = self.r0[i] ** 3
            floor = (R_MIN / tau[-1]) ** 3
            for j in kids:
                tk = tau[br[j].attach]
                rc = max(self.r0[j] * tk, R_MIN)
                d = (rc / tk) ** 3
                if remaining - d < floor:
                    drop.add(j)
                    continue
                remaining -= d
                cube -= d * _smoothstep((s - s[br[j].attach]) / 2.0)
                self.r0[j] = rc
            b.radius = np.maximum(np.cbrt(np.maximum(cube, 0.0)) * tau, R_MIN)  # active only on leaves
            for j, c in enumerate(br):  # children splitting the parent's end (the left main)
                if c.parent == i and c.attach >= len(s) - 1:
                    self.r0[j] = self.r0[j] * tau[-1]
        if drop:
            keep = [i for i in range(len(br)) if i not in drop]
            new_index = {old: new for new, old in enumerate(keep)}
            for i in keep:
                if br[i].parent >= 0:
                    br[i].parent = new_index[br[i].parent]
            self.tree.branches = [br[i] for i in keep]

    def child_radii(self, parent_r0: float, wanted: list[float], end_min: float) -> list[float]:
        """Scale the nominal child radii down until the parent keeps ≥ end_min after all of them."""
        wanted = np.asarray(wanted, float)
        budget = parent_r0**3 - end_min**3
        total = float((wanted**3).sum())
        if total > budget > 0:
            wanted = wanted * (budget / total) ** (1 / 3)
        return [max(float(w), R_MIN) for w in wanted]


# ---------------------------------------------------------------------------------------------- trees
def _left_tree(heart: Heart, rng: np.random.Generator, dominance: str) -> Tree:
    B = _Builder(heart, rng, "left")
    tl = heart.theta_lad
    r_lm = rng.uniform(2.0, 2.5)
    r_lad = min(rng.uniform(1.58, 2.05), r_lm * 0.85)  # × the LM taper (0.96) → Ø 3–4 mm
    ramus = rng.random() < 0.25
    r_ram = rng.uniform(0.8, 1.1) if ramus else 0.0
    r_lcx = float(np.cbrt(max(r_lm**3 - r_lad**3 - r_ram**3, (0.6 * r_lm) ** 3)))  # Murray at the LM split

    # left main: straight from the aortic root towards the split point on the AV groove
    theta_b = tl + math.radians(rng.uniform(12, 22))
    phi_b = math.radians(rng.uniform(2, 5))
    split = heart.surface(phi_b, theta_b, r_lm + 0.3)
    aorta = heart.base_centre - 14.0 * heart.u + 0.25 * heart.ra * heart.a - 0.1 * heart.rc * heart.c
    lm_len = rng.uniform(5, 15)
    direction = (aorta - split) / np.linalg.norm(aorta - split)
    n = int(lm_len / STEP_MM) + 1
    lm_pts = split + np.linspace(lm_len, 0, n)[:, None] * direction
    lm = B.add("LM", -1, lm_pts, np.full((n, 2), np.nan), r0=r_lm, taper=0.04)
    end = n - 1

    # LAD: turns from the split into the anterior groove, runs to the apex and a little around it
    lad_len = rng.uniform(100, 140)
    t = np.linspace(0, 1, 800)
    phi = phi_b + t * (math.pi - math.radians(rng.uniform(35, 55)) - phi_b)
    theta = tl + (theta_b - tl) * np.exp(-t / 0.04)
    lad = B.surface_branch("LAD", lm, end, phi, theta, 0.0, lad_len, r_lad, taper=0.2)

    # LCx: along the left AV groove (to the crux in left dominance)
    lcx_len = rng.uniform(60, 90)
    crux = tl + math.pi
    if dominance == "left":
        lcx_len = 1e9  # cut at the crux below
    t = np.linspace(0, 1, 800)
    theta = theta_b + t * (crux + math.radians(8) - theta_b)
    phi = phi_b + 0.02 * np.sin(np.pi * t)
    lcx = B.surface_branch("LCx", lm, end, phi, theta, 0.0, lcx_len, r_lcx, taper=0.15)

    if ramus:
        t = np.linspace(0, 1, 400)
        th = theta_b + t * math.radians(rng.uniform(25, 40))
        ph = phi_b + t * rng.uniform(0.7, 1.0)
        B.surface_branch("ramus", lm, end, ph, th, 0.0, rng.uniform(35, 60), r_ram, taper=0.3)

    # diagonals: from the proximal/mid LAD towards the lateral wall and the apex
    nd = int(rng.integers(1, 4))
    at = np.sort(rng.uniform(12, 60, nd))
    for k in range(1, nd):
        at[k] = max(at[k], at[k - 1] + 12)
    rs = B.child_radii(r_lad, [rng.uniform(0.9, 1.25) for _ in range(nd)] + [0.65, 0.65], 0.8)
    lad_b = B.tree.branches[lad]
    for k in range(nd):
        i = B.attach_point(lad, at[k])
        ph0, th0 = lad_b.params[i]
        t = np.linspace(0, 1, 400)
        th = th0 + t * math.radians(rng.uniform(35, 60))
        ph = ph0 + t * rng.uniform(0.35, 0.6)
        B.surface_branch(f"D{k + 1}", lad, i, ph, th, 0.0, rng.uniform(30, 60), rs[k], taper=0.3)

    # septal twigs: into the septum, 5 mm or more from the diagonals
    ns = int(rng.integers(2, 5))
    taken = list(at)
    for k in range(ns):
        for _ in range(20):
            pos = rng.uniform(8, 45)  # proximal LAD: thick enough to feed a twig (Murray)
            if all(abs(pos - q) > 6 for q in taken):
                break
        else:
            continue  # no room left on the proximal LAD
        taken.append(pos)
        i = B.attach_point(lad, pos)
        ph0, th0 = lad_b.params[i]
        t = np.linspace(0, 1, 200)
        depth = rng.uniform(10, 16)
        r = R_MIN + 0.05
        B.surface_branch(f"S{k + 1}", lad, i, ph0 + 0.12 * t, th0 + 0.0 * t, -(depth + 2 * r) * t,
                         rng.uniform(8, 15), r, taper=0.0, tort=0.3)

    # obtuse marginals from the LCx, down the lateral wall
    lcx_b = B.tree.branches[lcx]
    lcx_total = lcx_b.length
    nm = int(rng.integers(1, 4))
    lo, hi = 15.0, max(lcx_total - 12.0, 20.0)
    at = np.sort(rng.uniform(lo, hi, nm))
    for k in range(1, nm):
        at[k] = max(at[k], at[k - 1] + 12)
    at = at[at < lcx_total - 6]
    rs = B.child_radii(r_lcx, [rng.uniform(0.85, 1.2) for _ in at], 0.8)
    for k, pos in enumerate(at):
        i = B.attach_point(lcx, pos)
        ph0, th0 = lcx_b.params[i]
        t = np.linspace(0, 1, 400)
        ph = ph0 + t * rng.uniform(0.7, 1.0)
        th = th0 + t * math.radians(rng.uniform(-10, 12))
        B.surface_branch(f"OM{k + 1}", lcx, i, ph, th, 0.0, rng.uniform(30, 60), rs[k], taper=0.3)

    if dominance == "left":  # PDA from the LCx at the crux
        i = B.attach_point(lcx, lcx_total - 8.0)
        ph0, th0 = lcx_b.params[i]
        t = np.linspace(0, 1, 400)
        B.surface_branch("PDA", lcx, i, ph0 + t * 1.1, th0 + 0 * t + (crux - th0) * np.minimum(t * 8, 1), 0.0,
                         rng.uniform(40, 70), B.child_radii(r_lcx, [1.0], 0.8)[0], taper=0.35)
    B.assign_radii()
    return B.tree


def _right_tree(heart: Heart, rng: np.random.Generator, dominance: str) -> Tree:
    B = _Builder(heart, rng, "right")
    tl = heart.theta_lad
    crux = tl - math.pi  # same groove as the left tree's crux, reached going right
    r_rca = rng.uniform(1.75, 2.25)
    # RCA: from the aortic root (above the base, anterior-right) into the right AV groove to the crux
    th0 = tl - math.radians(rng.uniform(45, 60))
    rca_len = rng.uniform(100, 140)
    t = np.linspace(0, 1, 1200)
    extra = math.radians(rng.uniform(15, 30)) if dominance != "left" else 0.0
    theta = th0 + t * (crux - extra - th0)
    phi = -0.18 * np.exp(-t / 0.05) + math.radians(3) * (1 - np.exp(-t / 0.05))
    rca_curve = heart.surface(phi, theta, r_rca + 0.3)
    s = _arclength(rca_curve)
    s_crux = float(np.interp(crux, theta[::-1], s[::-1]))
    if dominance == "left":
        rca_len = min(rca_len, 0.7 * s_crux)
    else:
        # the RCA must pass the crux to give the PDA and continue as the posterolateral segment
        rca_len = float(np.clip(rca_len, s_crux + 12.0, s_crux + 30.0))
    rca = B.surface_branch("RCA", -1, -1, phi, theta, 0.0, rca_len, r_rca, taper=0.15)
    rca_b = B.tree.branches[rca]
    total = rca_b.length

    wanted, where = [], []
    # conus: first branch, over the right ventricular outflow tract
    wanted.append(rng.uniform(0.65, 0.85)); where.append(("conus", rng.uniform(4, 9)))
    nam = int(rng.integers(1, 4))
    span = (0.3 * min(total, s_crux), 0.85 * min(total, s_crux))
    at = np.sort(rng.uniform(*span, nam))
    for k in range(1, nam):
        at[k] = max(at[k], at[k - 1] + 12)
    for k in range(nam):
        wanted.append(rng.uniform(0.7, 1.0)); where.append((f"AM{k + 1}", float(at[k])))
    if dominance != "left":
        wanted.append(rng.uniform(0.95, 1.2)); where.append(("PDA", s_crux - 3.0))
        wanted.append(rng.uniform(0.8, 1.0)); where.append(("PLB", min(total - 6.0, s_crux + 8.0)))
    rs = B.child_radii(r_rca, wanted, 0.85)
    for (name, pos), r in zip(where, rs):
        i = B.attach_point(rca, pos)
        ph0, th0 = rca_b.params[i]
        t = np.linspace(0, 1, 400)
        if name == "conus":
            ph = ph0 + t * 0.25 + 0.06
            th = th0 + t * math.radians(rng.uniform(35, 50))
            length = rng.uniform(15, 30)
        elif name.startswith("AM"):
            ph = ph0 + t * rng.uniform(0.7, 1.0)
            th = th0 + t * math.radians(rng.uniform(5, 20))
            length = rng.uniform(30, 60)
        elif name == "PDA":
            ph = ph0 + t * 1.1
            th = th0 + (crux - th0) * np.minimum(t * 8, 1)
            length = rng.uniform(40, 80)
        else:  # PLB: along the groove a little further, then down the inferolateral LV wall
            ph = ph0 + t * 0.8
            th = th0 - t * math.radians(rng.uniform(10, 25))
            length = rng.uniform(25, 50)
        B.surface_branch(name, rca, i, ph, th, 0.0, length, r, taper=0.3)
    B.assign_radii()
    return B.tree


def _add_stenoses(tree: Tree, rng: np.random.Generator) -> None:
    """0–3 smooth stenoses on vessels of Ø ≥ 2 mm, away from branch points and ends."""
    n = int(rng.integers(0, 4))
    cands = [i for i, b in enumerate(tree.branches) if b.radius.max() >= 1.0 and b.length > 25]
    branch_pts = {i: [_arclength(tree.branches[i].points)[c.attach] for c in tree.branches if c.parent == i]
                  for i in cands}
    for _ in range(n):
        if not cands:
            break
        i = int(rng.choice(cands))
        b = tree.branches[i]
        s = _arclength(b.points)
        length = rng.uniform(3, 15)
        for _try in range(30):
            pos = rng.uniform(5 + length / 2, s[-1] - 5 - length / 2)
            ok = all(abs(pos - q) > length / 2 + 3 for q in branch_pts[i])
            ok &= all(abs(pos - st["position_mm"]) > (length + st["length_mm"]) / 2 + 3
                      for st in tree.stenoses if st["branch"] == b.name)
            if ok:
                break
        else:
            continue
        requested = rng.uniform(0.25, 0.90)
        k = int(np.argmin(np.abs(s - pos)))
        ref = float(b.radius[k])
        applied = float(min(requested, 1 - R_MIN_STENOSIS / ref))
        if applied < 0.2:
            continue
        x = (s - pos) / (length / 2)
        bump = np.where(np.abs(x) < 1, 0.5 * (1 + np.cos(np.pi * np.clip(x, -1, 1))), 0.0)
        b.radius = np.maximum(b.radius * (1 - applied * bump), R_MIN_STENOSIS)
        branch_pts[i].append(pos)
        tree.stenoses.append({
            "branch": b.name, "position_mm": float(pos), "length_mm": float(length),
            "centre": b.points[k].tolist(), "reference_diameter_mm": 2 * ref,
            "requested_reduction": float(requested), "diameter_reduction": applied,
        })


# ---------------------------------------------------------------------------------------------- anatomy
@dataclass
class LabelVolume:
    """A label volume with its index→world (LPS, mm) affine: world = affine @ [i, j, k, 1]."""

    data: np.ndarray
    affine: np.ndarray

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.affine[:3, :3], axis=0)


@dataclass
class CoronaryAnatomy:
    seed: int
    heart: Heart
    dominance: str
    left: Tree
    right: Tree

    def tree(self, side: str) -> Tree:
        return self.left if side == "left" else self.right

    def bounds(self, margin: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        pts = np.concatenate([b.points for t in (self.left, self.right) for b in t.branches])
        rad = np.concatenate([b.radius for t in (self.left, self.right) for b in t.branches])
        return (pts - rad[:, None]).min(0) - margin, (pts + rad[:, None]).max(0) + margin

    def label_volume(self, spacing=(0.4, 0.4, 0.45), shape=None, origin=None, margin_mm: float = 4.0) -> LabelVolume:
        """Voxelise both trees (voxel centre inside the union of balls → label 1 left / 2 right).

        Default: an axis-aligned crop around the trees with ``margin_mm`` of background. With ``shape``
        (and optionally ``origin``, the world position of voxel 0) a full-size volume, e.g. 512×512×256,
        centred on the trees when ``origin`` is None.
        """
        spacing = np.asarray(spacing, float).reshape(3)
        lo, hi = self.bounds(margin_mm)
        if shape is None:
            shape = np.ceil((hi - lo) / spacing).astype(int) + 1
            origin = lo if origin is None else np.asarray(origin, float)
        else:
            shape = np.asarray(shape, int)
            if origin is None:
                origin = (lo + hi) / 2 - (shape - 1) / 2 * spacing
        origin = np.asarray(origin, float)
        data = np.zeros(tuple(shape), np.uint8)
        for value, tree in ((1, self.left), (2, self.right)):
            pts, rad = tree.samples(0.2)
            _rasterise_balls(data, origin, spacing, pts, rad, value)
        affine = np.eye(4)
        affine[:3, :3] = np.diag(spacing)
        affine[:3, 3] = origin
        return LabelVolume(data, affine)

    def to_dict(self) -> dict:
        return {"seed": self.seed, "dominance": self.dominance, "heart": self.heart.to_dict(),
                "left": [b.name for b in self.left.branches], "right": [b.name for b in self.right.branches]}


def _rasterise_balls(data, origin, spacing, pts, rad, value, chunk: int = 400):
    """Set ``data`` to ``value`` at voxels whose centre lies in any ball (pts, rad)."""
    shape = np.asarray(data.shape)
    for s0 in range(0, len(pts), chunk):
        p, r = pts[s0:s0 + chunk], rad[s0:s0 + chunk]
        k = np.ceil(r.max() / spacing).astype(int) + 1
        off = np.stack(np.meshgrid(*[np.arange(-kk, kk + 1) for kk in k], indexing="ij"), -1).reshape(-1, 3)
        base = np.rint((p - origin) / spacing).astype(int)
        idx = base[:, None, :] + off[None]
        world = origin + idx * spacing
        inside = np.linalg.norm(world - p[:, None, :], axis=2) <= r[:, None]
        inside &= np.all((idx >= 0) & (idx < shape), axis=2)
        sel = idx[inside]
        data[sel[:, 0], sel[:, 1], sel[:, 2]] = value


def _min_gap(a: Tree, b: Tree) -> float:
    from scipy.spatial import cKDTree

    pa, ra = a.samples(1.0)
    pb, rb = b.samples(1.0)
    d, i = cKDTree(pb).query(pa)
    return float((d - ra - rb[i]).min())


def generate(seed: int, dominance: Optional[str] = None) -> CoronaryAnatomy:
    """A random, anatomically plausible pair of coronary trees; the same seed gives the same anatomy."""
    for attempt in range(20):
        rng = np.random.default_rng([int(seed), attempt])
        heart = random_heart(rng)
        dom = dominance or str(rng.choice(["right", "co", "left"], p=[0.8, 0.1, 0.1]))
        left = _left_tree(heart, rng, dom)
        right = _right_tree(heart, rng, dom)
        _add_stenoses(left, rng)
        _add_stenoses(right, rng)
        # the two trees must stay apart (≥ 3 mm wall to wall) so a binary mask separates into two components
        if _min_gap(left, right) >= 3.0:
            return CoronaryAnatomy(int(seed), heart, dom, left, right)
    raise RuntimeError(f"seed {seed}: no anatomy with separated trees after 20 attempts")


# ---------------------------------------------------------------------------------------------- shape shift
@dataclass(frozen=True)
class ShapeShift:
    """Anatomy outside the generator's range, to test a method on shapes it was not trained on.

    Applied to a generated anatomy (:func:`shape_shifted`): everything scaled about the heart centre by
    ``scale`` (longer vessels: the LAD becomes 120–168 mm against 100–140 mm), radii × ``radius_scale``
    (thinner: the smallest vessels Ø 0.84 mm against 1.2 mm), and a smooth random displacement field of
    ``waves`` plane waves per axis (amplitude ``amplitude_mm`` each, wavelength ``wavelength_mm``) on top of the
    generator's own tortuosity — a spatial field, so every child stays attached to its parent.
    """

    scale: float = 1.2
    radius_scale: float = 0.7
    amplitude_mm: float = 0.8
    wavelength_mm: tuple[float, float] = (10.0, 16.0)
    waves: int = 3


def shape_shifted(anatomy: CoronaryAnatomy, shift: ShapeShift = ShapeShift(), seed: int = 0) -> CoronaryAnatomy:
    """A copy of ``anatomy`` with :class:`ShapeShift` applied (seeded; the trees kept ≥ 3 mm apart)."""
    import copy

    centre = anatomy.heart.base_centre + 0.4 * anatomy.heart.length * anatomy.heart.u
    for attempt in range(20):
        rng = np.random.default_rng([int(seed), 4242, attempt])
        k = rng.normal(size=(3, shift.waves, 3))
        k /= np.linalg.norm(k, axis=2, keepdims=True)
        k *= (2 * np.pi / rng.uniform(*shift.wavelength_mm, size=(3, shift.waves)))[..., None]
        phase = rng.uniform(0, 2 * np.pi, size=(3, shift.waves))

        def warp(x):
            d = np.stack([(shift.amplitude_mm * np.sin(x @ k[a].T + phase[a])).sum(1) for a in range(3)], axis=1)
            return centre + shift.scale * (x - centre) + d

        out = copy.deepcopy(anatomy)
        for tree in (out.left, out.right):
            for b in tree.branches:
                b.points = warp(b.points)
                b.radius = b.radius * shift.radius_scale
            for st in tree.stenoses:
                st["centre"] = warp(np.asarray(st["centre"], float)[None])[0].tolist()
                st["reference_diameter_mm"] *= shift.radius_scale
                st["position_mm"] *= shift.scale
                st["length_mm"] *= shift.scale
        if _min_gap(out.left, out.right) >= 3.0:
            return out
    raise RuntimeError(f"seed {seed}: no shape-shifted anatomy with separated trees after 20 attempts")

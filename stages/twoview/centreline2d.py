"""2D vessel centrelines of one view: ordered sub-pixel branches with tangent and lumen radius.

Reads: a vessel mask (H×W bool) and optionally the segmenter's vessel probability (H×W float in [0, 1]).
Writes: nothing (a :class:`Centreline2D` in memory).

Steps (:func:`extract_centreline`):

1. foreground = the mask, plus pixels of probability ≥ ``low`` connected to it (hysteresis), so thin and
   faint vessels that the 0.5 threshold breaks up survive;
2. thinning (:func:`skimage.morphology.skeletonize`), then the skeleton cut into chains between junctions
   and ends (a junction = a cluster of skeleton pixels with three or more neighbours);
3. short terminal spurs (shorter than the vessel is wide) dropped, and the catheter (long straight chains
   and the chains along their lines, :mod:`stages.core.catheter`): a segmenter keeps it, and in one view it
   finds partners among the other view's vessels;
4. each chain smoothed (Gaussian along the chain) and resampled at 1 px arc steps: sub-pixel points and
   unit tangents;
5. lumen radius from the profile across the vessel: the integral of the (bilinearly interpolated) mask or
   probability along the normal over the run that contains the centre point — sub-pixel, unbiased on
   average for a binary silhouette — smoothed along the branch.

Image indices are (row, col), pixel centres at integer indices.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..core.catheter import along_lines, catheter_lines
from ..core.errors import UserError

__all__ = ["Centreline2D", "extract_centreline"]

_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


@dataclass
class Centreline2D:
    """Branches of one view's vessel centreline, points ordered along each branch (1 px steps)."""

    points: np.ndarray  # N×2 float (row, col)
    tangent: np.ndarray  # N×2 unit vectors (row, col) along the branch order
    radius_px: np.ndarray  # N lumen radius in pixels
    branch: np.ndarray  # N int branch id; a branch's points are contiguous and ordered
    ends: np.ndarray  # B×2 int node id at the first and last point of each branch (shared at junctions)
    shape: tuple[int, int] = (0, 0)
    node_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # node id → (row, col)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def n_branches(self) -> int:
        return len(self.ends)

    def branch_slices(self) -> list[slice]:
        """The index range of every branch (points of a branch are contiguous)."""
        if len(self.branch) == 0:
            return []
        starts = np.flatnonzero(np.r_[True, np.diff(self.branch) != 0])
        stops = np.r_[starts[1:], len(self.branch)]
        return [slice(int(a), int(b)) for a, b in zip(starts, stops)]

    def length_px(self) -> float:
        return float(sum(max(s.stop - s.start - 1, 0) for s in self.branch_slices()))


def _foreground(mask: np.ndarray, prob: np.ndarray | None, low: float) -> np.ndarray:
    fg = np.asarray(mask, bool)
    if prob is not None:
        weak = np.asarray(prob, float) >= low
        lab, n = ndimage.label(weak | fg, structure=np.ones((3, 3)))
        if n:
            keep = np.zeros(n + 1, bool)
            keep[np.unique(lab[fg])] = True
            keep[0] = False
            fg = keep[lab]
    return fg


def _chains(skel: np.ndarray):
    """Cut a 1-px skeleton into chains. Returns (chains: list of K×2 int pixel arrays, chain_ends: list of
    (node_a, node_b), node_points: list of (row, col), n_junctions: the first n_junctions nodes are
    junction clusters, the rest free ends)."""
    rr, cc = np.nonzero(skel)
    if len(rr) == 0:
        return [], [], [], 0
    count = ndimage.convolve(skel.astype(np.uint8), np.ones((3, 3), np.uint8), mode="constant") - 1
    junction = skel & (count >= 3)
    jlab, n_junctions = ndimage.label(junction, structure=np.ones((3, 3)))
    node_points = [tuple(p) for p in ndimage.center_of_mass(junction, jlab, range(1, n_junctions + 1))]
    body = skel & ~junction
    index = -np.ones(skel.shape, np.int64)
    index[body] = np.arange(int(body.sum()))
    pix = np.argwhere(body)
    H, W = skel.shape

    def body_neighbours(r, c):
        out = []
        for dr, dc in _NEIGHBOURS:
            r2, c2 = r + dr, c + dc
            if 0 <= r2 < H and 0 <= c2 < W and index[r2, c2] >= 0:
                out.append(index[r2, c2])
        return out

    def junction_next_to(r, c):
        for dr, dc in _NEIGHBOURS:
            r2, c2 = r + dr, c + dc
            if 0 <= r2 < H and 0 <= c2 < W and jlab[r2, c2] > 0:
                return int(jlab[r2, c2]) - 1
        return None

    nbrs = [body_neighbours(r, c) for r, c in pix]
    seen = np.zeros(len(pix), bool)
    chains, chain_ends = [], []
    order = sorted(range(len(pix)), key=lambda i: len(nbrs[i]) != 1)  # start at chain ends first
    for start in order:
        if seen[start]:
            continue
        path = [start]
        seen[start] = True
        cur = start
        while True:
            nxt = [j for j in nbrs[cur] if not seen[j]]
            if not nxt:
                break
            # prefer the 4-connected neighbour (skeleton staircases offer both)
            nxt.sort(key=lambda j: abs(pix[j][0] - pix[cur][0]) + abs(pix[j][1] - pix[cur][1]))
            cur = nxt[0]
            seen[cur] = True
            path.append(cur)
        if len(nbrs[start]) > 1 and len(path) > 1:
            # started inside a chain (a loop or a chain whose ends both touch junctions): walk the other way
            back, cur = [], start
            while True:
                nxt = [j for j in nbrs[cur] if not seen[j]]
                if not nxt:
                    break
                cur = nxt[0]
                seen[cur] = True
                back.append(cur)
            path = back[::-1] + path
        pts = pix[path]
        ends = []
        for r, c in (pts[0], pts[-1]):
            j = junction_next_to(r, c)
            if j is None:
                node_points.append((float(r), float(c)))
                j = len(node_points) - 1
            ends.append(j)
        # junction clusters sit at the chain's ends: include their centre so branches meet
        if ends[0] < n_junctions:
            pts = np.vstack([np.asarray(node_points[ends[0]])[None], pts])
        if ends[1] < n_junctions:
            pts = np.vstack([pts, np.asarray(node_points[ends[1]])[None]])
        chains.append(np.asarray(pts, float))
        chain_ends.append((ends[0], ends[1]))
    return chains, chain_ends, node_points, n_junctions


def _catheter_chains(chains, shape) -> list[bool]:
    """Per chain: is it catheter (:mod:`stages.core.catheter`, the strict rule)? A long straight chain entering
    from the image edge is one, and so is any chain lying along its line (the catheter cut into pieces by the
    vessels crossing it)."""
    lines = catheter_lines(chains, shape)
    return [along_lines(pts, lines) for pts in chains] if lines else [False] * len(chains)


def _without_catheter(chains, chain_ends, shape):
    """The chains that are not catheter, and their ends."""
    keep = [not c for c in _catheter_chains(chains, shape)]
    return [c for c, k in zip(chains, keep) if k], [e for e, k in zip(chain_ends, keep) if k]


def catheter_pixels(skeleton: np.ndarray) -> np.ndarray:
    """H×W boolean: the pixels of a vessel mask's skeleton that belong to a catheter by the strict rule (the
    chains :func:`extract_centreline` leaves out)."""
    skeleton = np.asarray(skeleton, bool)
    out = np.zeros(skeleton.shape, bool)
    if not skeleton.any():
        return out
    chains = _chains(skeleton)[0]
    for pts, is_catheter in zip(chains, _catheter_chains(chains, skeleton.shape)):
        if is_catheter:
            rc = np.rint(pts).astype(np.int64)
            out[rc[:, 0], rc[:, 1]] = True
    return out


def _resample(pts: np.ndarray, step: float = 1.0, sigma: float = 1.5) -> np.ndarray:
    if len(pts) >= 3 and sigma > 0:
        sm = ndimage.gaussian_filter1d(pts, sigma, axis=0, mode="nearest")
        sm[0], sm[-1] = pts[0], pts[-1]  # keep the ends on the junction / tip
        pts = sm
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    if s[-1] < 1e-9:
        return pts[:1]
    n = max(int(round(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def _profile_radius(field_img: np.ndarray, points: np.ndarray, normals: np.ndarray, reach: np.ndarray,
                    step: float = 0.25) -> np.ndarray:
    """Half the integral of the field across the vessel, over the contiguous run around each point."""
    n_steps = int(np.ceil(reach.max() / step)) if len(reach) else 1
    offs = np.arange(-n_steps, n_steps + 1) * step
    coords = points[:, None, :] + offs[None, :, None] * normals[:, None, :]
    vals = ndimage.map_coordinates(field_img, [coords[..., 0].ravel(), coords[..., 1].ravel()], order=1,
                                   mode="constant", cval=0.0).reshape(len(points), len(offs))
    vals = np.where(np.abs(offs)[None, :] <= reach[:, None], vals, 0.0)
    centre = n_steps
    inside = vals > 0.02
    # the run containing the centre: stop at the first sample on each side that leaves the vessel
    right = np.cumprod(inside[:, centre:], axis=1).astype(bool)
    left = np.cumprod(inside[:, centre::-1], axis=1).astype(bool)
    total = (vals[:, centre:] * right).sum(1) + (vals[:, centre::-1] * left).sum(1) - vals[:, centre] * inside[:, centre]
    return 0.5 * total * step


def extract_centreline(mask, prob=None, *, low: float = 0.3, min_spur_px: float = 4.0, smooth_px: float = 1.5,
                       max_hole_px: int = 4, drop_catheter: bool = True, source: str = "mask") -> Centreline2D:
    """The centreline branches of one view (see the module docstring). ``source`` names the view in errors.
    ``drop_catheter``: leave out the pieces :mod:`stages.core.catheter` takes for a catheter."""
    from skimage.morphology import skeletonize

    mask = np.asarray(mask, bool)
    if mask.ndim != 2:
        raise UserError(f"{source}: a vessel mask must be 2D, got shape {mask.shape}")
    fg = _foreground(mask, prob, low)
    if not fg.any():
        return Centreline2D(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int32),
                            np.zeros((0, 2), np.int32), mask.shape)
    # pinholes only: a loop of vessels crossing each other must stay open (filling it makes a blob)
    holes = ndimage.binary_fill_holes(fg) & ~fg
    lab, n = ndimage.label(holes)
    if n:
        small = np.bincount(lab.ravel(), minlength=n + 1) <= max_hole_px
        small[0] = False
        fg = fg | small[lab]
    skel = skeletonize(fg)
    edt = ndimage.distance_transform_edt(fg)
    chains, chain_ends, node_points, n_junctions = _chains(skel)
    if drop_catheter:
        chains, chain_ends = _without_catheter(chains, chain_ends, mask.shape)
    node_points = np.asarray(node_points, float).reshape(-1, 2)
    degree = np.zeros(len(node_points), int)
    for a, b in chain_ends:
        degree[a] += 1
        degree[b] += 1
    field_img = np.clip(np.asarray(prob, float), 0, 1) if prob is not None else fg.astype(float)
    field_img = np.where(fg, np.maximum(field_img, 0.5), field_img) if prob is not None else field_img
    pts_all, tan_all, rad_all, br_all, ends = [], [], [], [], []
    for pts, (a, b) in zip(chains, chain_ends):
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
        width = 2.0 * float(np.median(edt[pts[:, 0].round().astype(int).clip(0, mask.shape[0] - 1),
                                          pts[:, 1].round().astype(int).clip(0, mask.shape[1] - 1)]))
        terminal = degree[a] == 1 or degree[b] == 1
        if (terminal and degree[a] + degree[b] > 2 and length < max(min_spur_px, width)) or length < 1.0:
            continue  # a spur off a junction (mask bump), or a lone dot
        res = _resample(pts, 1.0, smooth_px)
        if len(res) < 2:
            continue
        tan = np.gradient(res, axis=0)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
        normals = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
        ri = res.round().astype(int)
        ri[:, 0] = ri[:, 0].clip(0, mask.shape[0] - 1)
        ri[:, 1] = ri[:, 1].clip(0, mask.shape[1] - 1)
        reach = 2.0 * edt[ri[:, 0], ri[:, 1]] + 3.0
        rad = _profile_radius(field_img, res, normals, reach)
        # across a junction or a crossing the profile spans both vessels: take the radius from the
        # branch's points beyond it (interpolated along the branch)
        near = np.zeros(len(res), bool)
        for node in (a, b):
            if node < n_junctions:
                near |= np.linalg.norm(res - node_points[node], axis=1) < 1.5 * np.median(rad) + 2.0
        if near.any() and (~near).sum() >= 2:
            k = np.arange(len(res))
            rad = np.where(near, np.interp(k, k[~near], rad[~near]), rad)
        elif near.all():
            rad = np.full(len(res), min(float(np.median(rad)), float(np.median(edt[ri[:, 0], ri[:, 1]]))))
        if len(rad) >= 5:
            rad = ndimage.median_filter(rad, size=5, mode="nearest")
        rad = ndimage.uniform_filter1d(rad, size=3, mode="nearest")
        br = len(ends)
        pts_all.append(res)
        tan_all.append(tan)
        rad_all.append(np.maximum(rad, 0.5))
        br_all.append(np.full(len(res), br, np.int32))
        ends.append((a, b))
    if not pts_all:
        return Centreline2D(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int32),
                            np.zeros((0, 2), np.int32), mask.shape, node_points)
    return Centreline2D(np.concatenate(pts_all), np.concatenate(tan_all), np.concatenate(rad_all),
                        np.concatenate(br_all), np.asarray(ends, np.int32).reshape(-1, 2), mask.shape,
                        np.asarray(node_points, float).reshape(-1, 2))

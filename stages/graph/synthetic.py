"""Synthetic inputs for testing and benchmarking the graph optimisation (reads/writes nothing).

* :func:`synthetic_tree` — a smooth random vessel tree (main branch and side branches, tapering radii) as a
  :class:`~stages.graph.vascular.VascularGraph`, placed near the isocentre;
* :func:`voxelise_prediction` — that tree as a network-like sparse prediction at 0.5 mm: soft
  ``occupancy`` (a sigmoid of the signed distance to the lumen, optionally noisy) and ``centreness``
  (1 − d/r clipped to [0, 1]) on the lumen plus a band of outside voxels;
* :func:`smooth_warp` — a known smooth deformation (rotation about a centre + a sinusoidal bend +
  translation) standing in for cardiac motion between key frames;
* :func:`render_mask` — the binary 2D vessel mask of a graph seen by a :class:`~stages.core.geometry.Camera`
  (disc splatting of the projected lumen), standing in for a segmentation;
* :func:`moving_case` — all of the above as key frames of one moving tree (the benchmark's case), and
  :func:`tracking_errors`, tracked graphs scored against the true trees.

The real pipeline gets these from the SBP network, the motion model and the segmentation stage.
"""

from __future__ import annotations

import numpy as np

from .vascular import VascularGraph

__all__ = ["synthetic_tree", "voxelise_prediction", "smooth_warp", "render_mask", "moving_case", "tracking_errors"]


def _unit(v):
    return v / np.linalg.norm(v)


def synthetic_tree(seed: int = 0, n_side: int = 4, main_length: float = 90.0, step: float = 0.5,
                   centre=(0.0, 0.0, 0.0), r_root: float = 2.0) -> VascularGraph:
    """A random smooth tree: one main branch of ``main_length`` mm and ``n_side`` side branches.

    Side branches leave the main branch (or an earlier side branch) 40–70° off its direction, at least
    12 mm apart along the parent, so bifurcations are well separated; radii taper and follow a
    Murray-like split (children ≈ 0.75 of the parent). Nodes every ``step`` mm.
    """
    rng = np.random.default_rng(seed)
    nodes: list[np.ndarray] = []
    radius: list[float] = []
    edges: list[tuple[int, int]] = []
    branches: list[list[int]] = []

    def grow(p0, d0, r0, length, parent_node):
        d = _unit(np.asarray(d0, float))
        curl = _unit(np.cross(d, rng.normal(size=3)))
        p = np.asarray(p0, float)
        idx = []
        n = int(length / step)
        prev = parent_node
        for i in range(n):
            # smooth curvature: rotate the direction slowly towards a drifting normal
            curl = _unit(curl + 0.15 * rng.normal(size=3) - (curl @ d) * d)
            d = _unit(d + 0.012 * curl * (step / 0.5))
            p = p + step * d
            nodes.append(p.copy())
            radius.append(max(r0 * (1.0 - 0.4 * (i + 1) / n), 0.7))
            k = len(nodes) - 1
            if prev is not None:
                edges.append((prev, k))
            prev = k
            idx.append(k)
        branches.append(idx)
        return idx

    root = np.asarray(centre, float) + np.array([-30.0, -10.0, 35.0]) + rng.normal(0, 2, 3)
    nodes.append(root)
    radius.append(r_root)
    main = grow(root, [0.6, -0.2, -0.8], r_root, main_length, 0)
    parents = [(main, main_length)]
    attempts = 0
    used_at: list[np.ndarray] = [root]
    while len(branches) < n_side + 1 and attempts < 200:
        attempts += 1
        par, plen = parents[int(rng.integers(len(parents)))]
        j = int(rng.integers(int(0.15 * len(par)), int(0.8 * len(par))))
        at = par[j]
        if min(np.linalg.norm(nodes[at] - q) for q in used_at) < 12.0:
            continue
        t = _unit(nodes[par[min(j + 1, len(par) - 1)]] - nodes[par[max(j - 1, 0)]])
        side = _unit(np.cross(t, rng.normal(size=3)))
        ang = np.radians(rng.uniform(40, 70))
        d = np.cos(ang) * t + np.sin(ang) * side
        length = rng.uniform(25, 45) if par is main else rng.uniform(15, 25)
        child = grow(nodes[at], d, 0.75 * radius[at], length, at)
        used_at.append(nodes[at])
        if par is main:
            parents.append((child, length))
    return VascularGraph(np.array(nodes), np.array(radius), np.array(edges, np.int64))


def _band_voxels(points, reach: float, voxel_size, origin):
    """Voxel indices within about ``reach`` mm of the points (a superset; EDT of the points' voxels)."""
    from scipy.ndimage import distance_transform_edt

    idx = np.rint((points - origin) / voxel_size).astype(np.int64)
    pad = int(np.ceil(reach / voxel_size)) + 2
    lo = idx.min(0) - pad
    shape = tuple((idx.max(0) + pad - lo + 1).tolist())
    seed = np.ones(shape, bool)
    seed[tuple((idx - lo).T)] = False
    near = distance_transform_edt(seed) * voxel_size <= reach + voxel_size
    return np.argwhere(near) + lo


def voxelise_prediction(graph: VascularGraph, voxel_size: float = 0.5, band_mm: float = 1.5, softness_mm: float = 0.2,
                        noise: float = 0.0, seed: int = 0, origin=None):
    """A SparseVoxels prediction of the graph's lumen (features ``occupancy``, ``centreness`` in [0, 1])."""
    from scipy.spatial import cKDTree

    from ..core.voxels import SparseVoxels

    pts, rad = graph.sample(0.05)
    origin = np.floor(pts.min(0) / voxel_size) * voxel_size - 4 * voxel_size if origin is None else np.asarray(origin, float)
    coords = _band_voxels(pts, float(rad.max()) + band_mm, voxel_size, origin)
    X = origin + coords * voxel_size
    d, i = cKDTree(pts).query(X, workers=2)
    r = rad[i]
    keep = d <= r + band_mm
    coords, d, r = coords[keep], d[keep], r[keep]
    occ = 1.0 / (1.0 + np.exp(-(r - d) / softness_mm))
    cen = np.clip(1.0 - d / r, 0.0, 1.0)
    if noise > 0:
        rng = np.random.default_rng(seed)
        occ = np.clip(occ + rng.normal(0, noise, len(occ)), 0, 1)
        cen = np.clip(cen + rng.normal(0, noise, len(cen)), 0, 1)
    return SparseVoxels(coords.astype(np.int32), voxel_size, origin,
                        {"occupancy": occ.astype(np.float32), "centreness": cen.astype(np.float32)})


def _rotation(axis, angle_deg):
    a = _unit(np.asarray(axis, float))
    th = np.radians(angle_deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def smooth_warp(points, centre, angle_deg: float = 8.0, axis=(0.3, 0.2, 1.0), bend_mm: float = 3.0,
                bend_dir=(0.0, 1.0, 0.0), bend_axis=(0.0, 0.0, 1.0), bend_period_mm: float = 120.0,
                translation=(1.5, -1.0, 2.0)):
    """Known smooth deformation: rotate about ``centre``, bend (displacement ``bend_mm``·sin along
    ``bend_axis`` in direction ``bend_dir``), translate. Returns the warped N×3 points."""
    X = np.asarray(points, float)
    c = np.asarray(centre, float)
    Y = (X - c) @ _rotation(axis, angle_deg).T + c
    s = (X - c) @ _unit(np.asarray(bend_axis, float))
    Y = Y + bend_mm * np.sin(2 * np.pi * s / bend_period_mm)[:, None] * _unit(np.asarray(bend_dir, float))
    return Y + np.asarray(translation, float)


def render_mask(graph: VascularGraph, camera, step: float = 0.2) -> np.ndarray:
    """H×W uint8 mask: union of the projected lumen discs along the centreline (radius scaled by depth)."""
    pts, rad = graph.sample(step)
    rc, depth = camera.project(pts, return_depth=True)
    focal = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    rpx = rad * focal / depth
    mask = np.zeros((camera.rows, camera.cols), np.uint8)
    ok = np.isfinite(rc).all(1)
    rc, rpx = rc[ok], rpx[ok]
    k = int(np.ceil(rpx.max())) + 1 if len(rpx) else 0
    off = np.stack(np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij"), -1).reshape(-1, 2)
    for chunk in np.array_split(np.arange(len(rc)), max(1, len(rc) // 4000)):
        base = np.rint(rc[chunk]).astype(np.int64)
        cand = base[:, None, :] + off[None]
        inside = np.linalg.norm(cand - rc[chunk][:, None, :], axis=2) <= rpx[chunk][:, None]
        c = cand[inside]
        c = c[(c[:, 0] >= 0) & (c[:, 0] < camera.rows) & (c[:, 1] >= 0) & (c[:, 1] < camera.cols)]
        mask[c[:, 0], c[:, 1]] = 1
    return mask


def moving_case(seed: int = 7, n_frames: int = 4):
    """(tree, key frames, true trees): a coronary-sized tree (120 mm main branch, 10 side branches) moved
    through ``n_frames`` key frames by :func:`smooth_warp` (up to 9° rotation, 3.5 mm bend, 3 mm translation),
    each a :class:`~stages.graph.io.PredictionFrame` of a noisy prediction and two 512² masks
    (LAO 30/CRA 20, RAO 35/CAU 15)."""
    from ..core.geometry import Camera
    from .io import PredictionFrame

    tree = synthetic_tree(seed, n_side=10, main_length=120.0)
    cams = {"a": Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512),
            "b": Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512)}
    frames, truths = [], []
    for k, s in enumerate(np.linspace(0, 1, n_frames)):
        t = tree.copy(nodes=smooth_warp(tree.nodes, tree.nodes.mean(0), angle_deg=9 * s, bend_mm=3.5 * s,
                                        translation=(1.5 * s, -1.0 * s, 2.5 * s)))
        truths.append(t)
        frames.append(PredictionFrame(f"kf{k}", voxelise_prediction(t, noise=0.05, seed=k),
                                      {v: render_mask(t, c) for v, c in cams.items()}, cams))
    return tree, frames, truths


def tracking_errors(graphs, truths) -> list[dict]:
    """Per key frame, tracked graph against true tree (mm): nodes, bifurcations found and true, distance of
    each node to the true centreline (mean, p95), correspondence error (each node against the true position,
    in this frame, of the truth node nearest to it in the first frame: sliding along a vessel counts) and
    median radius error."""
    from scipy.spatial import cKDTree

    ref = cKDTree(truths[0].nodes).query(graphs[0].nodes)[1]
    out = []
    for g, t in zip(graphs, truths):
        d = cKDTree(t.sample(0.1)[0]).query(g.nodes)[0]
        r_err = np.abs(g.radius - t.radius[cKDTree(t.nodes).query(g.nodes)[1]])
        out.append(dict(nodes=len(g), bifurcations=len(g.bifurcations()), true_bifurcations=len(t.bifurcations()),
                        dist_mean=float(d.mean()), dist_p95=float(np.percentile(d, 95)),
                        correspondence=float(np.linalg.norm(g.nodes - t.nodes[ref], axis=1).mean()),
                        radius_median=float(np.median(r_err))))
    return out

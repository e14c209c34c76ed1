"""Graph updating (paper, "Graph optimization"): fit a deformation graph so a vascular graph matches the
next key frame, then chain through all key frames so one topology is tracked through the cycle.

:func:`register_graph` alternates

* **match** — every curve segment of the warped graph is matched by the Algorithm-1 DP
  (:mod:`stages.graph.matching`) to the 3D target points (the next frame's predicted centreline) and,
  per view, its projection to the view's 2D vessel centreline pixels;
* **update** — L-BFGS (SciPy's L-BFGS-B, gradients in closed form) on

      E = mean_i ρ(‖x'_i − m_i‖) + w_2D · mean_{v,i} ρ(s_v ‖π_v(x'_i) − m^v_i‖) + λ_reg · E_reg / |edges|

  with ρ the Huber loss (δ = ``huber_mm``); 2D residuals are converted from pixels to mm with each
  view's isocentre pixel spacing ``s_v`` so both terms are commensurate. ``λ_reg`` decreases over the
  outer iterations (stiff first, as in non-rigid ICP) so large rigid-like motion is found before local
  bending. ``E_reg`` carries a small rotation-smoothness term (``rotation_weight``; why:
  :meth:`DeformationGraph.regulariser`): without it data-re showed node rotations of up to 165°
  where 10–30° fit as well.

:func:`optimise_frames` runs it key frame after key frame (frame k−1's tracked graph → frame k), lets
vessel pieces first seen in a later frame join the tracked topology (added in that frame and carried
back to earlier frames through the inverse warps, so every frame has the same nodes and edges; a piece that
attaches nowhere and lies more than ``max_float_mm`` = 10 mm from the tracked tree stays out: seen in one
key frame only and floating, it is what a ghost of that frame's prediction looks like, and the quality
check, :mod:`stages.quality`, flags exactly such pieces; the bundled example carried two, 15 and 9 mm
long, 30–47 mm from its tree), and
fuses node radii from the 3D prediction (lumen distance at the frame's own graph) and the 2D masks
(Euclidean distance transform of each mask at the projected node, pixels → mm at the node's depth).

Reads/writes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..core.catheter import CATHETER
from .deformation import DeformationGraph
from .matching import Targets, match_graph
from .redundancy import FAR_PIECE_MM
from .vascular import VascularGraph

__all__ = ["View", "FrameInput", "RegistrationResult", "TrackedGraphs", "register_graph", "optimise_frames",
           "mask_centreline", "radius_from_masks"]


@dataclass
class View:
    """One X-ray view of a key frame: its camera and 2D vessel centreline pixels (M×2, (row, col)).

    ``mask`` (H×W, optional) is used for radii, ``image`` (H×W, optional: the X-ray frame) for the image
    contrast, ``catheter`` (H×W bool, optional) marks the mask's pixels that are the catheter the run showed before
    its contrast arrived. :meth:`from_mask` thins a mask to its centreline.
    """

    camera: object
    centreline_rc: np.ndarray
    mask: np.ndarray | None = None
    image: np.ndarray | None = None
    catheter: np.ndarray | None = None

    @classmethod
    def from_mask(cls, camera, mask, image=None) -> "View":
        """The view of a labelled mask (:func:`stages.core.catheter.vessel_labels`: non-zero is vessel)."""
        labels = np.asarray(mask)
        catheter = labels == CATHETER
        mask = labels > 0
        return cls(camera, mask_centreline(mask), mask, image, catheter if catheter.any() else None)

    @cached_property
    def contrast(self) -> np.ndarray | None:
        """H×W log contrast of the image's dark structures (:func:`stages.segment.vesselness.log_contrast`, the
        background over 8 mm at the isocentre, at least 15 px); None without an image (computed once per view)."""
        from ..segment.vesselness import log_contrast

        if self.image is None:
            return None
        return log_contrast(self.image, max(15, round(8.0 / self.camera.isocentre_spacing)))

    @cached_property
    def centreline_distance(self) -> np.ndarray:
        """H×W distance (px) from every pixel to the nearest centreline pixel (computed once per view)."""
        from scipy.ndimage import distance_transform_edt

        on = np.zeros((self.camera.rows, self.camera.cols), bool)
        rc = np.rint(np.asarray(self.centreline_rc)).astype(np.int64)
        on[rc[:, 0], rc[:, 1]] = True
        return distance_transform_edt(~on)

    @cached_property
    def centreline_lines(self):
        """(a KD-tree of the centreline pixels, M×2 unit normals): each pixel's line across the vessel, from the
        principal direction of it and its six nearest centreline pixels (computed once per view)."""
        from scipy.spatial import cKDTree

        points = np.asarray(self.centreline_rc, float).reshape(-1, 2)
        tree = cKDTree(points)
        if len(points) < 2:
            return tree, np.zeros((len(points), 2))
        _, neighbours = tree.query(points, k=min(7, len(points)))
        offsets = points[neighbours] - points[neighbours].mean(1, keepdims=True)
        _, vectors = np.linalg.eigh(np.einsum("mki,mkj->mij", offsets, offsets))
        return tree, vectors[:, :, 0]  # the smaller eigenvalue's direction: across the vessel

    @cached_property
    def mask_distance(self) -> np.ndarray:
        """H×W distance (px) from every pixel to the vessel mask (0 inside; computed once per view)."""
        from scipy.ndimage import distance_transform_edt

        return distance_transform_edt(~(np.asarray(self.mask) > 0))

    @cached_property
    def catheter_distance(self) -> np.ndarray | None:
        """H×W distance (px) from every pixel to the catheter's pixels; None without them (computed once per view)."""
        from scipy.ndimage import distance_transform_edt

        return None if self.catheter is None else distance_transform_edt(~self.catheter)

    @cached_property
    def depth_in_mask(self) -> np.ndarray | None:
        """H×W distance (px) from every mask pixel to the nearest background pixel (0 outside: the lumen's 2D
        half-width on the vessel's ridge); None without a mask (computed once per view)."""
        from scipy.ndimage import distance_transform_edt

        return None if self.mask is None else distance_transform_edt(np.asarray(self.mask) > 0)

    @cached_property
    def ridge_radius(self) -> np.ndarray | None:
        """:attr:`depth_in_mask` raised to its 3×3 maximum inside the mask, so that a point a pixel off the ridge
        still reads the ridge (0 outside; None without a mask; computed once per view)."""
        from scipy.ndimage import maximum_filter

        if self.mask is None:
            return None
        return np.where(np.asarray(self.mask) > 0, maximum_filter(self.depth_in_mask, size=3), 0.0)


def mask_centreline(mask: np.ndarray) -> np.ndarray:
    """(row, col) pixels of the 2D skeleton of a vessel mask (pixel centres at integer indices)."""
    from skimage.morphology import skeletonize

    return np.argwhere(skeletonize(np.asarray(mask) > 0)).astype(float)


@dataclass
class RegistrationResult:
    graph: VascularGraph  # the warped source graph (same topology and node ids)
    deformation: DeformationGraph  # with fitted params
    history: list[dict] = field(default_factory=list)


def _lbfgs(value_and_grad, params: np.ndarray, iterations: int) -> np.ndarray:
    """Minimise a function of ``params`` (any shape) by SciPy's L-BFGS-B; ``value_and_grad(params)`` returns the
    value and its gradient (same shape). Returns the minimiser, shaped like ``params``."""
    from scipy.optimize import minimize

    shape = params.shape

    def fun(x):
        value, grad = value_and_grad(x.reshape(shape))
        return value, grad.ravel()

    res = minimize(fun, np.asarray(params, float).ravel(), jac=True, method="L-BFGS-B",
                   options={"maxiter": iterations, "maxfun": int(1.25 * iterations) + 1, "maxcor": 20,
                            "gtol": 1e-9, "ftol": 1e-12})
    return res.x.reshape(shape)


class _Warp:
    """The warp a registration stage fits, with its gradient in closed form: fixed points ``x`` (N×3) move by
    x' = Σ_j W_ij (R_j x + b_j), b_j = g_j + t_j − R_j g_j, for per-node parameters P (M×6: axis-angle,
    translation) of nodes ``g``; with ``deformation``, plus its rigidity regulariser / |edges|.

    A rigid motion about the centroid c is the one-node case (g = c, W = 1). Closed-form gradients, because the
    registration evaluates its energy about a thousand times per case and autograd spent ~1.5 ms on each
    (graph building on a few hundred small tensors), several times the arithmetic."""

    def __init__(self, points: np.ndarray, nodes: np.ndarray, weights: np.ndarray,
                 deformation: DeformationGraph | None = None, rotation_weight: float = 0.0):
        from scipy.sparse import csr_matrix

        self.x = np.asarray(points, float)
        self.g = np.asarray(nodes, float).reshape(-1, 3)
        self.W = np.asarray(weights, float)  # N×M, rows sum to one
        self.edges = np.zeros((0, 2), np.int64) if deformation is None else deformation.edges
        M, E = len(self.g), len(self.edges)
        if E:
            j, k = self.edges[:, 0], self.edges[:, 1]
            ones = np.ones(E)
            self.S_j = csr_matrix((ones, (j, np.arange(E))), shape=(M, E))  # edge → its start node
            self.S_jk = self.S_j - csr_matrix((ones, (k, np.arange(E))), shape=(M, E))
            self.rot_w = rotation_weight * deformation.sigma ** 2

    @classmethod
    def rigid(cls, points: np.ndarray) -> "_Warp":
        """One rotation about the points' centroid and a translation."""
        points = np.asarray(points, float)
        return cls(points, points.mean(0, keepdims=True), np.ones((len(points), 1)))

    @classmethod
    def of_deformation(cls, points: np.ndarray, deformation: DeformationGraph, rotation_weight: float = 0.0):
        """The deformation graph's warp of fixed points (:meth:`DeformationGraph.warp`) and its regulariser."""
        points = np.asarray(points, float)
        idx, w = deformation.weights(points)
        W = np.zeros((len(points), len(deformation)))
        np.add.at(W, (np.arange(len(points))[:, None], idx), w)
        return cls(points, deformation.nodes, W, deformation, rotation_weight)

    def positions(self, P: np.ndarray, R: np.ndarray) -> np.ndarray:
        b = self.g + P[:, 3:] - np.einsum("mij,mj->mi", R, self.g)
        Y = self.W @ np.concatenate([R.reshape(-1, 9), b], 1)
        return np.einsum("nij,nj->ni", Y[:, :9].reshape(-1, 3, 3), self.x) + Y[:, 9:]

    def backward(self, grad_X: np.ndarray):
        """dE/dR (M×3×3) and dE/dt (M×3) from dE/dx' (N×3)."""
        grad_Y = np.concatenate([(grad_X[:, :, None] * self.x[:, None, :]).reshape(-1, 9), grad_X], 1)
        grad_A = self.W.T @ grad_Y
        grad_b = grad_A[:, 9:]
        return grad_A[:, :9].reshape(-1, 3, 3) - grad_b[:, :, None] * self.g[:, None, :], grad_b

    def regulariser(self, P: np.ndarray, R: np.ndarray):
        """E_reg / |edges| (:meth:`DeformationGraph.regulariser`) and its gradients (dE/dR, dE/dt)."""
        M = len(self.g)
        if not len(self.edges):
            return 0.0, np.zeros((M, 3, 3)), np.zeros((M, 3))
        j, k = self.edges[:, 0], self.edges[:, 1]
        n = len(self.edges)
        v = self.g[k] - self.g[j]
        e = np.einsum("eij,ej->ei", R[j], v) + self.g[j] + P[j, 3:] - self.g[k] - P[k, 3:]
        D = R[j] - R[k]
        energy = float((e * e).sum() + self.rot_w * (D * D).sum()) / n
        grad_R = (self.S_j @ (2 * e[:, :, None] * v[:, None, :]).reshape(-1, 9)
                  + self.S_jk @ (2 * self.rot_w * D).reshape(-1, 9)).reshape(M, 3, 3) / n
        return energy, grad_R, (self.S_jk @ (2 * e)) / n


def _huber(d: np.ndarray, delta: float):
    """Huber loss of distances and its derivative."""
    return np.where(d <= delta, 0.5 * d * d, delta * (d - 0.5 * delta)), np.minimum(d, delta)


def _project(camera, X: np.ndarray):
    """(row, col) of world points and what the chain rule needs: homogeneous image points h and K·R."""
    KR = np.asarray(camera.K, float) @ np.asarray(camera.R, float)
    h = (X - np.asarray(camera.source, float)) @ KR.T
    return np.stack([h[:, 1] / h[:, 2], h[:, 0] / h[:, 2]], 1), h, KR


def _project_backward(grad_rc: np.ndarray, h: np.ndarray, KR: np.ndarray) -> np.ndarray:
    """dE/dX (N×3) from dE/d(row, col) (N×2) through :func:`_project` (its ``h`` and ``KR``)."""
    g_row, g_col = grad_rc[:, 0] / h[:, 2], grad_rc[:, 1] / h[:, 2]
    return np.stack([g_col, g_row, -(g_col * h[:, 0] + g_row * h[:, 1]) / h[:, 2]], 1) @ KR


def register_graph(source: VascularGraph, target_points=None, views: list[View] | tuple = (), *,
                   deformation: DeformationGraph | None = None, spacing_mm: float = 5.0, knn: int = 6,
                   rigid_iterations: int = 10, outer_iterations: int = 10, lbfgs_iterations: int = 10,
                   reg_start: float = 3.0, reg_end: float = 0.3, w2d: float = 1.0, huber_mm: float = 3.0,
                   dp_lam: float = 2.0, dp_k: int = 8, max_match_mm: float = 10.0, null_cost_mm: float | None = 5.0,
                   w_reverse: float = 0.5, landmark_weight: float = 5.0, tol_mm: float = 0.05,
                   step_mm: float | None = 1.0, rotation_weight: float = 0.1) -> RegistrationResult:
    """Deform ``source`` onto 3D ``target_points`` (P×3 mm) and/or 2D ``views`` (see module docstring).

    A rigid stage comes first (one rotation about the graph's centroid + a translation, the same
    match → L-BFGS loop for up to ``rigid_iterations``), then the deformation graph, initialised to
    that rigid motion, for up to ``outer_iterations`` match → update rounds with ``λ_reg`` going
    geometrically from ``reg_start`` to ``reg_end``. Loops stop early once no node moves more than
    ``tol_mm``. Distances, δ and costs in mm (2D ones converted with each view's isocentre spacing).
    Matched residuals of end points weigh ``landmark_weight`` times more (they fix sliding along the
    vessels); the reverse (target → node) term, weight ``w_reverse``, keeps curve ends from stopping short.
    The fit runs on the graph decimated to about one node per ``step_mm`` (None: every node); the
    fitted deformation then moves every node. ``rotation_weight`` (0.1) weighs neighbouring nodes'
    rotation differences in ``E_reg`` (chosen on data-re, Table 2's L8: 3D centreline error 3.23 → 3.16 mm,
    accuracy unchanged, EPE within noise; 1.0 gave the same 3D gain with noisier 2D scores).
    """
    fit_graph = source if step_mm is None else source.decimate(step_mm)[0]
    if deformation is None:
        deformation = DeformationGraph.from_graph(source, spacing_mm=spacing_mm, k=knn)
    reg = _Registration(fit_graph, target_points, views, dp_lam, dp_k, max_match_mm, null_cost_mm, w2d,
                        huber_mm, w_reverse, landmark_weight)
    res = reg.run(deformation, rigid_iterations, outer_iterations, lbfgs_iterations, reg_start, reg_end, tol_mm,
                  rotation_weight)
    if fit_graph is not source:
        res.graph = source.copy(nodes=res.deformation.warp(source.nodes))
    return res


class _Registration:
    def __init__(self, source, target_points, views, dp_lam, dp_k, max_match_mm, null_cost_mm, w2d, huber_mm,
                 w_reverse, landmark_weight):
        self.w_reverse = w_reverse
        self.landmark_weight = landmark_weight
        # end points pin the motion along the vessels, which curve matching barely sees (measured: weighting
        # junctions instead did not help)
        self.node_weight = np.where(source.degrees() == 1, landmark_weight, 1.0)
        self.source = source
        self.segments = source.segments()
        self.T3 = Targets(target_points) if target_points is not None and len(target_points) else None
        self.views = [(v, Targets(v.centreline_rc), float(v.camera.isocentre_spacing)) for v in views
                      if len(v.centreline_rc)]
        self.match_kw = dict(k=dp_k, lam=dp_lam)
        self.max_match_mm, self.null_cost_mm = max_match_mm, null_cost_mm
        self.w2d, self.huber_mm = w2d, huber_mm
        self.history: list[dict] = []

    def match(self, Xw):
        """Residual terms (kind, node indices, matched targets, camera, mm per unit) at positions Xw."""
        terms = []
        if self.T3 is not None:
            m3 = match_graph(Xw, self.segments, self.T3, max_dist=self.max_match_mm, null_cost=self.null_cost_mm,
                             **self.match_kw)
            ok = np.isfinite(m3).all(1)
            if ok.any():
                terms.append(("3d", np.flatnonzero(ok), m3[ok], None, 1.0))
            rev = self.reverse(Xw, self.T3.points, self.null_cost_mm or self.max_match_mm)
            if rev is not None:
                terms.append(("3d-rev",) + rev + (None, 1.0))
        for v, T2, s in self.views:
            rc = v.camera.project(Xw)
            m2 = match_graph(rc, self.segments, T2, max_dist=self.max_match_mm / s,
                             null_cost=None if self.null_cost_mm is None else self.null_cost_mm / s, **self.match_kw)
            ok = np.isfinite(m2).all(1) & np.isfinite(rc).all(1)
            if ok.any():
                terms.append(("2d", np.flatnonzero(ok), m2[ok], v.camera, s))
            if self.w_reverse > 0 and np.isfinite(rc).all():
                rev = self.reverse(rc, T2.points, (self.null_cost_mm or self.max_match_mm) / s)
                if rev is not None:
                    terms.append(("2d-rev",) + rev + (v.camera, s))
        return terms

    def reverse(self, Xw, targets, gate):
        """Target → nearest node pairs within ``gate`` (the coverage direction of a symmetric match, so
        curve ends do not stop short of the target's ends)."""
        from scipy.spatial import cKDTree

        if self.w_reverse <= 0:
            return None
        d, i = cKDTree(Xw).query(targets, distance_upper_bound=gate)
        ok = np.isfinite(d)
        if not ok.any():
            return None
        return i[ok], targets[ok]

    def data_energy(self, X: np.ndarray, terms):
        """E_data at node positions X (N×3) and its gradient dE/dX: each term is the mean Huber loss of its
        residuals (mm), weighted as the module docstring says."""
        energy = 0.0
        grad_X = np.zeros_like(X)
        projected = {}  # camera → (rc, h, K·R, dE/d(row, col)): all nodes projected once per camera
        for kind, sel, target, cam, s in terms:
            if kind.startswith("2d"):
                if id(cam) not in projected:
                    projected[id(cam)] = (*_project(cam, X), np.zeros((len(X), 2)))
                p, sink = projected[id(cam)][0][sel], projected[id(cam)][3]
            else:
                p, sink = X[sel], grad_X
            diff = p - target
            length = np.sqrt((diff * diff).sum(1) + 1e-12)
            rho, drho = _huber(length * s, self.huber_mm)
            w = 1.0 if kind.startswith("3d") else self.w2d
            if kind.endswith("rev"):
                w = w * self.w_reverse
            elif self.landmark_weight != 1.0:
                rho, drho = rho * self.node_weight[sel], drho * self.node_weight[sel]
            energy += w * float(rho.mean())
            np.add.at(sink, sel, (w / len(sel) * s) * (drho / length)[:, None] * diff)
        for rc, h, KR, grad_rc in projected.values():
            grad_X += _project_backward(grad_rc, h, KR)
        return energy, grad_X

    def loop(self, stage, warp: _Warp, params, iterations, lbfgs_iterations, lambdas, tol_mm):
        """match → L-BFGS rounds on ``warp``'s parameters; returns the final parameters and warped positions."""
        from .deformation import rodrigues, rodrigues_backward

        prev = warp.positions(params, rodrigues(params[:, :3]))
        for it in range(iterations):
            terms = self.match(prev)
            if not terms:
                break
            lam = float(lambdas[it])

            def value_and_grad(P):
                R = rodrigues(P[:, :3])
                e_data, grad_X = self.data_energy(warp.positions(P, R), terms)
                e_reg, reg_R, reg_t = warp.regulariser(P, R)
                grad_R, grad_t = warp.backward(grad_X)
                grad_R, grad_t = grad_R + lam * reg_R, grad_t + lam * reg_t
                return e_data + lam * e_reg, np.hstack([rodrigues_backward(P[:, :3], grad_R), grad_t])

            params = _lbfgs(value_and_grad, params, lbfgs_iterations)
            R = rodrigues(params[:, :3])
            Xw = warp.positions(params, R)
            e_data, e_reg = self.data_energy(Xw, terms)[0], warp.regulariser(params, R)[0]
            moved = float(np.abs(Xw - prev).max())
            prev = Xw
            self.history.append({"stage": stage, "iteration": it, "lambda_reg": lam, "data": e_data, "reg": e_reg,
                                 "matched": {t[0]: int(len(t[1])) for t in terms}, "max_move_mm": moved})
            if moved < tol_mm:
                break
        return params, prev

    def run(self, deformation, rigid_iterations, outer_iterations, lbfgs_iterations, reg_start, reg_end, tol_mm,
            rotation_weight=0.0):
        from .deformation import rodrigues

        X0 = self.source.nodes
        init = deformation.params.copy()
        # ---- rigid stage: x' = R(x − c) + c + t
        if rigid_iterations > 0 and not np.any(init):
            rigid = _Warp.rigid(X0)
            theta, _ = self.loop("rigid", rigid, np.zeros((1, 6)), rigid_iterations, lbfgs_iterations,
                                 np.zeros(rigid_iterations), tol_mm)
            th, c = theta[0], rigid.g[0]
            R = rodrigues(th[:3])[0]
            g = deformation.nodes
            init = np.hstack([np.tile(th[:3], (len(g), 1)), (g - c) @ R.T + c + th[3:] - g])
        # ---- deformation graph, stiff → flexible
        warp = _Warp.of_deformation(X0, deformation, rotation_weight)
        lambdas = np.geomspace(reg_start, reg_end, outer_iterations) if outer_iterations > 1 else [reg_end]
        params, warped = self.loop("deformation", warp, init, outer_iterations, lbfgs_iterations, lambdas, tol_mm)
        deformation.params = params.copy()
        return RegistrationResult(self.source.copy(nodes=warped), deformation, self.history)


# ---------------------------------------------------------------------------------------------- radii
def radius_from_masks(points: np.ndarray, views: list[View]) -> np.ndarray:
    """Per point, the smallest 2D lumen radius over the views (mm; NaN where no mask covers the point).

    The EDT of the mask (distance to the nearest background pixel centre, which lies just beyond the
    edge) near the projected point (3×3 maximum, so a node a pixel off the ridge still reads the ridge),
    times the pixel size at the point's depth. The minimum over views resists overlap, which only widens
    a vessel's 2D extent.
    """
    from scipy.ndimage import map_coordinates

    P = np.asarray(points, float)
    best = np.full(len(P), np.nan)
    for v in views:
        if v.mask is None:
            continue
        edt = v.ridge_radius
        rc, depth = v.camera.project(P, return_depth=True)
        ok = np.isfinite(rc).all(1) & v.camera.in_image(rc)
        val = np.full(len(P), np.nan)
        val[ok] = map_coordinates(edt, rc[ok].T, order=1, mode="constant")
        focal = 0.5 * (v.camera.K[0, 0] + v.camera.K[1, 1])
        r = val * depth / focal
        r[~(val >= 1.0)] = np.nan  # outside (or on the rim of) the mask: no measurement
        best = np.fmin(best, r)
    return best


def _smooth_along_edges(values: np.ndarray, edges: np.ndarray, iterations: int = 2) -> np.ndarray:
    v = values.copy()
    if not len(edges):
        return v
    for _ in range(iterations):
        s = v.copy()
        c = np.ones(len(v))
        np.add.at(s, edges[:, 0], v[edges[:, 1]])
        np.add.at(s, edges[:, 1], v[edges[:, 0]])
        np.add.at(c, edges[:, 0], 1)
        np.add.at(c, edges[:, 1], 1)
        v = s / c
    return v


def fuse_radius(points: np.ndarray, edges: np.ndarray, frame_graph: VascularGraph | None, views, fallback: np.ndarray,
                max_dist_mm: float = 2.0) -> np.ndarray:
    """Radius per tracked node from the frame's own 3D graph (nearest point within ``max_dist_mm``) and the
    2D masks; the mean of the available estimates, else ``fallback``; lightly smoothed along the edges."""
    from scipy.spatial import cKDTree

    r3 = np.full(len(points), np.nan)
    if frame_graph is not None and len(frame_graph):
        fp, fr = frame_graph.sample(0.25)
        d, i = cKDTree(fp).query(points)
        r3 = np.where(d <= max_dist_mm, fr[i], np.nan)
    r2 = radius_from_masks(points, views) if views else np.full(len(points), np.nan)
    stack = np.vstack([r3, r2])
    finite = np.isfinite(stack)
    have = finite.any(0)
    # mean of the finite estimates per node, without nanmean's warning for nodes that have none
    mean = np.where(finite, stack, 0.0).sum(0) / np.maximum(finite.sum(0), 1)
    fused = np.where(have, mean, fallback)
    return np.maximum(_smooth_along_edges(fused, edges), 0.1)


# ---------------------------------------------------------------------------------------------- chaining
@dataclass
class FrameInput:
    """One key frame: a key, its predicted graph (from :func:`~stages.graph.init.init_graph`) and views."""

    key: str
    graph: VascularGraph
    views: list[View] = field(default_factory=list)


@dataclass
class TrackedGraphs:
    """Graphs of every key frame with one shared topology (same edges and ``node_id`` in every frame)."""

    keys: list[str]
    graphs: list[VascularGraph]
    deformations: list[DeformationGraph | None]  # deformations[k] takes frame k−1 to frame k (None for the first)
    first_frame: np.ndarray  # per node, the frame index where it was first seen
    histories: list[list[dict]] = field(default_factory=list)


def _join_new_pieces(tracked: VascularGraph, frame_graph: VascularGraph, join_dist_mm: float, min_piece_mm: float,
                      max_float_mm: float = np.inf):
    """Pieces of ``frame_graph`` that ``tracked`` does not cover, as (positions, radius, internal edges,
    attachments [(new local index, tracked node index)]). A piece that attaches nowhere and lies farther
    than ``max_float_mm`` from ``tracked`` is left out."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if not len(frame_graph) or not len(tracked):
        return []
    tp, _ = tracked.sample(0.5)
    d, _ = cKDTree(tp).query(frame_graph.nodes)
    new = d > np.maximum(join_dist_mm, 1.5 * frame_graph.radius)
    if not new.any():
        return []
    e = frame_graph.edges
    inner = e[new[e[:, 0]] & new[e[:, 1]]]
    n = len(frame_graph)
    ncomp, lab = connected_components(coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])), shape=(n, n)),
                                      directed=False)
    node_tree = cKDTree(tracked.nodes)
    pieces = []
    for c in np.unique(lab[new]):
        members = np.flatnonzero(new & (lab == c))
        local = -np.ones(n, np.int64)
        local[members] = np.arange(len(members))
        pe = inner[(lab[inner[:, 0]] == c)]
        length = np.linalg.norm(frame_graph.nodes[pe[:, 0]] - frame_graph.nodes[pe[:, 1]], axis=1).sum()
        if length < min_piece_mm:
            continue
        # attach where the frame graph leaves the covered part (an edge from a new node to a covered one)
        border = e[new[e[:, 0]] != new[e[:, 1]]]
        attach = []
        for a, b in border:
            inside, outside = (a, b) if local[a] >= 0 else (b, a)
            if local[inside] >= 0 and lab[inside] == c:
                attach.append((int(local[inside]), int(node_tree.query(frame_graph.nodes[outside])[1])))
        if not attach and node_tree.query(frame_graph.nodes[members])[0].min() > max_float_mm:
            continue
        pieces.append((frame_graph.nodes[members], frame_graph.radius[members], local[pe], attach))
    return pieces


def optimise_frames(frames: list[FrameInput], *, reference: int = 0, refine_reference: bool = True,
                    join_dist_mm: float = 2.0, min_new_piece_mm: float = 5.0, max_float_mm: float = FAR_PIECE_MM,
                    progress=None,
                    **register_kw) -> TrackedGraphs:
    """Track one vascular topology through the key frames (see the module docstring).

    ``frames[reference].graph`` is the template. Each later frame is reached from the previous one by
    :func:`register_graph` against that frame's graph points (3D) and views (2D); frames before the
    reference are reached backwards in the same way. ``register_kw`` go to :func:`register_graph`.
    """
    K = len(frames)
    if K == 0:
        raise ValueError("no key frames")
    template = frames[reference].graph
    if not len(template):
        raise ValueError(f"key frame {frames[reference].key!r} has an empty graph: nothing to track")
    graphs: list[VascularGraph | None] = [None] * K
    defs: list[DeformationGraph | None] = [None] * K
    hists: list[list[dict]] = [[] for _ in range(K)]
    first = np.full(len(template), reference, np.int64)

    def targets_of(k):
        g = frames[k].graph
        return g.sample(0.5)[0] if len(g) else None

    g0 = template.copy()
    if refine_reference and frames[reference].views:
        res = register_graph(g0, targets_of(reference), frames[reference].views, **register_kw)
        g0, hists[reference] = res.graph, res.history
    g0 = g0.copy(radius=fuse_radius(g0.nodes, g0.edges, frames[reference].graph, frames[reference].views, g0.radius))
    graphs[reference] = g0
    next_id = int(g0.node_id.max()) + 1 if len(g0) else 0

    def carry(pos, k):
        """Positions of points seen in frame k, in every frame already tracked (through the warps)."""
        out = {k: pos}
        if k > reference:
            for j in range(k, reference, -1):  # defs[j] takes j−1 → j
                out[j - 1] = defs[j].inverse_warp(out[j])
        else:
            for j in range(k, reference):  # defs[j] takes j+1 → j
                out[j + 1] = defs[j].inverse_warp(out[j])
            for j in range(reference + 1, K):
                if defs[j] is not None:
                    out[j] = defs[j].warp(out[j - 1])
        return out

    order = list(range(reference + 1, K)) + list(range(reference - 1, -1, -1))
    for step, k in enumerate(order):
        src = graphs[k - 1 if k > reference else k + 1]
        res = register_graph(src, targets_of(k), frames[k].views, **register_kw)
        defs[k], hists[k] = res.deformation, res.history
        graphs[k] = res.graph
        # vessel pieces seen first in this frame join the topology, carried back to the frames already done
        for pos, rad, pe, attach in _join_new_pieces(graphs[k], frames[k].graph, join_dist_mm, min_new_piece_mm,
                                                            max_float_mm):
            base = len(graphs[k])
            edges = np.vstack([graphs[k].edges, pe + base] + [np.array([[base + a, t]]) for a, t in attach])
            ids = np.r_[graphs[k].node_id, np.arange(next_id, next_id + len(pos))]
            next_id += len(pos)
            first = np.r_[first, np.full(len(pos), k)]
            for j, p in carry(pos, k).items():
                gj = graphs[j]
                graphs[j] = VascularGraph(np.vstack([gj.nodes, p]), np.r_[gj.radius, rad], edges, ids)
        g = graphs[k]
        graphs[k] = g.copy(radius=fuse_radius(g.nodes, g.edges, frames[k].graph, frames[k].views, g.radius))
        if progress is not None:
            progress(step + 1, len(order))
    return TrackedGraphs([f.key for f in frames], graphs, defs, first, hists)

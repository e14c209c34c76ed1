"""Deformation graph (paper Eqs. 12–13, 15–16): a coarse graph of nodes g_j, each with a rotation R_j
(axis-angle, 3 parameters) and a translation t_j, warping any point x by

    x' = Σ_j w_j(x) [R_j (x − g_j) + g_j + t_j],   w_j(x) ∝ exp(−‖x − g_j‖² / (2σ²))

over its ``n_anchors`` nearest nodes (less the weight of the next nearest, so the warp stays continuous
where the anchor set changes; then normalised to sum to one), with the rigidity regulariser

    E_reg = Σ_j Σ_{k ∈ N(j)} ‖R_j (g_k − g_j) + g_j + t_j − (g_k + t_k)‖²

on the k-nearest-neighbour edges, optionally plus w·σ²·‖R_j − R_k‖²_F (rotation smoothness: Eq. 13 alone
leaves a twist about the line through collinear neighbours free). Rotations are axis-angle (Rodrigues),
so they stay orthonormal and need no orthogonality term. Reads/writes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .vascular import VascularGraph

__all__ = ["DeformationGraph", "rodrigues", "rodrigues_backward"]


def rodrigues(r: np.ndarray) -> np.ndarray:
    """M×3 axis-angle vectors → M×3×3 rotation matrices (NumPy)."""
    r = np.asarray(r, float).reshape(-1, 3)
    th2 = (r * r).sum(1)
    th = np.sqrt(th2)
    small = th2 < 1e-8
    a = np.where(small, 1 - th2 / 6, np.sin(th) / np.where(small, 1, th))
    b = np.where(small, 0.5 - th2 / 24, (1 - np.cos(th)) / np.where(small, 1, th2))
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _vee(H: np.ndarray) -> np.ndarray:
    """M×3×3 → M×3: the inner products ⟨H, E_i⟩ with the generators E_i = ∂K/∂r_i of the skew matrix K(r)."""
    return np.stack([H[:, 2, 1] - H[:, 1, 2], H[:, 0, 2] - H[:, 2, 0], H[:, 1, 0] - H[:, 0, 1]], 1)


def rodrigues_backward(r: np.ndarray, grad_R: np.ndarray) -> np.ndarray:
    """The gradient of a scalar with respect to axis-angle vectors r (M×3), given its gradient with respect to
    their rotations :func:`rodrigues` (M×3×3): the chain rule through R = I + a(θ²) K + b(θ²) K²."""
    r = np.asarray(r, float).reshape(-1, 3)
    th2 = (r * r).sum(1)
    th = np.sqrt(th2)
    small = th2 < 1e-8
    safe = np.where(small, 1.0, th2)
    a = np.where(small, 1 - th2 / 6, np.sin(th) / np.where(small, 1, th))
    b = np.where(small, 0.5 - th2 / 24, (1 - np.cos(th)) / safe)
    da = np.where(small, -1 / 6, (np.cos(th) - a) / (2 * safe))  # d a / d θ²
    db = np.where(small, -1 / 24, (a - 2 * b) / (2 * safe))  # d b / d θ²
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    G = np.asarray(grad_R, float).reshape(-1, 3, 3)
    KT = K.transpose(0, 2, 1)
    g_K = (G * K).sum((1, 2))
    g_KK = (G * (K @ K)).sum((1, 2))
    # ⟨G, E_i K + K E_i⟩ = ⟨G Kᵀ + Kᵀ G, E_i⟩
    return (2 * r * (da * g_K + db * g_KK)[:, None] + a[:, None] * _vee(G)
            + b[:, None] * _vee(G @ KT + KT @ G))


@dataclass
class DeformationGraph:
    """Nodes ``nodes`` (M×3 mm), k-NN ``edges`` (P×2, j → k), Gaussian width ``sigma`` (mm) and the per-node
    parameters ``params`` (M×6: axis-angle rotation in radians, translation in mm)."""

    nodes: np.ndarray
    edges: np.ndarray
    sigma: float
    params: np.ndarray | None = None
    n_anchors: int = 4
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self.nodes = np.asarray(self.nodes, float).reshape(-1, 3)
        self.edges = np.asarray(self.edges, np.int64).reshape(-1, 2)
        self.params = np.zeros((len(self.nodes), 6)) if self.params is None else np.asarray(self.params, float).reshape(-1, 6)

    def __len__(self) -> int:
        return len(self.nodes)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_points(cls, points: np.ndarray, spacing_mm: float = 5.0, k: int = 6, sigma: float | None = None,
                    n_anchors: int = 4) -> "DeformationGraph":
        """Nodes on a coarse grid: per occupied ``spacing_mm`` cell, the point nearest the cell's mean."""
        from scipy.spatial import cKDTree

        P = np.asarray(points, float).reshape(-1, 3)
        if not len(P):
            raise ValueError("cannot build a deformation graph from no points")
        cell = np.floor(P / spacing_mm).astype(np.int64)
        _, inv = np.unique(cell, axis=0, return_inverse=True)
        inv = inv.ravel()
        m = inv.max() + 1
        mean = np.zeros((m, 3))
        np.add.at(mean, inv, P)
        mean /= np.bincount(inv, minlength=m)[:, None]
        d = np.linalg.norm(P - mean[inv], axis=1)
        order = np.lexsort((d, inv))  # per cell, the nearest point first
        first = order[np.r_[True, inv[order][1:] != inv[order][:-1]]]
        nodes = P[first]
        kk = min(k, len(nodes) - 1)
        if kk > 0:
            _, nb = cKDTree(nodes).query(nodes, kk + 1)
            edges = np.stack([np.repeat(np.arange(len(nodes)), kk), nb[:, 1:].ravel()], 1)
        else:
            edges = np.zeros((0, 2), np.int64)
        return cls(nodes, edges, float(sigma if sigma is not None else spacing_mm), None, n_anchors)

    @classmethod
    def from_graph(cls, g: VascularGraph, spacing_mm: float = 5.0, k: int = 6, sigma: float | None = None,
                   n_anchors: int = 4) -> "DeformationGraph":
        """Deformation graph sampled from a vascular graph (its edges sampled every 0.5 mm)."""
        pts, _ = g.sample(0.5)
        return cls.from_points(pts, spacing_mm, k, sigma, n_anchors)

    # ---------------------------------------------------------------- weights and warps
    def weights(self, points: np.ndarray):
        """(anchor indices P×K, normalised Gaussian weights P×K) of arbitrary points."""
        from scipy.spatial import cKDTree

        P = np.asarray(points, float).reshape(-1, 3)
        K = min(self.n_anchors, len(self.nodes))
        Kq = min(K + 1, len(self.nodes))
        d, idx = cKDTree(self.nodes).query(P, Kq)
        d, idx = d.reshape(len(P), Kq), idx.reshape(len(P), Kq)
        # shift by the nearest distance so far-away points still get finite, normalisable weights
        w = np.exp(-(d ** 2 - d[:, :1] ** 2) / (2 * self.sigma ** 2))
        if Kq > K:
            # subtract the first excluded node's weight: weights reach zero exactly where the anchor set
            # changes, so the warp is continuous (and invertible by fixed-point iteration)
            w = np.maximum(w[:, :K] - w[:, K:], 0.0)
            idx = idx[:, :K]
        flat = w.sum(1) <= 1e-12  # equidistant anchors: fall back to uniform weights
        w[flat] = 1.0
        return idx, w / w.sum(1, keepdims=True)

    def warp(self, points: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
        """Warped positions x' of N×3 points (NumPy)."""
        P = np.asarray(points, float).reshape(-1, 3)
        params = self.params if params is None else np.asarray(params, float)
        idx, w = self.weights(P)
        R = rodrigues(params[:, :3])
        g = self.nodes[idx]  # P×K×3
        local = np.einsum("pkij,pkj->pki", R[idx], P[:, None, :] - g) + g + params[idx, 3:]
        return (w[..., None] * local).sum(1)

    def inverse_warp(self, points: np.ndarray, iterations: int = 30, tol_mm: float = 1e-4) -> np.ndarray:
        """Approximate pre-image x of warped points y (warp(x) = y).

        Starts from the best iterate of the fixed-point iteration x ← y − u(x), then takes damped Newton
        steps with a finite-difference Jacobian: a point's step is halved until its residual ‖warp(x) − y‖
        drops, and every point keeps the best position found. On its own the fixed-point iteration
        diverges wherever the displacement changes by more than 1 mm per mm (a node rotated by tens of
        degrees does that): it threw carried-back vessel pieces hundreds of mm away.
        Where the warp folds, the pre-image found is the one reached from y itself.
        """
        Y = np.asarray(points, float).reshape(-1, 3)
        X = Y.copy()
        if not len(Y):
            return X
        res = self.warp(X) - Y
        err = np.linalg.norm(res, axis=1)
        # start from the best iterate of the fixed-point iteration, which is right wherever the warp is mild
        Z = X.copy()
        for _ in range(10):
            Z = Y - (self.warp(Z) - Z)
            r_z = self.warp(Z) - Y
            e_z = np.linalg.norm(r_z, axis=1)
            better = e_z < err
            X[better], res[better], err[better] = Z[better], r_z[better], e_z[better]
        step_scale = np.ones(len(Y))
        h = 1e-3  # mm; the warp is smooth at this scale except where an anchor set changes
        for _ in range(iterations):
            active = err > tol_mm
            if not active.any():
                break
            Xa, ra = X[active], res[active]
            base = self.warp(Xa)
            J = np.stack([(self.warp(Xa + h * e) - base) / h for e in np.eye(3)], -1)  # n×3×3, column = ∂/∂x_i
            ok = np.abs(np.linalg.det(J)) > 1e-6
            step = -ra  # a fixed-point step where the Jacobian is singular
            if ok.any():
                step[ok] = -np.linalg.solve(J[ok], ra[ok][:, :, None])[:, :, 0]
            # a trust region: a near-singular Jacobian (a fold) must not send the point far off
            length = np.linalg.norm(step, axis=1)
            step *= np.minimum(1.0, 2 * err[active] / np.maximum(length, 1e-12))[:, None]
            trial = Xa + step_scale[active, None] * step
            r_trial = self.warp(trial) - Y[active]
            e_trial = np.linalg.norm(r_trial, axis=1)
            better = e_trial < err[active]
            idx = np.flatnonzero(active)
            X[idx[better]], res[idx[better]], err[idx[better]] = trial[better], r_trial[better], e_trial[better]
            step_scale[idx[better]] = np.minimum(step_scale[idx[better]] * 2, 1.0)
            step_scale[idx[~better]] *= 0.5
            if (step_scale[active] < 1e-4).all():
                break
        return X

    def regulariser(self, params: np.ndarray | None = None, rotation_weight: float = 0.0) -> float:
        """E_reg of ``params`` (default: the graph's own), mm² (module docstring); the registration fits it with its
        gradient (:class:`stages.graph.optimise._Warp`)."""
        params = self.params if params is None else params
        if not len(self.edges):
            return 0.0
        j, k = self.edges[:, 0], self.edges[:, 1]
        R = rodrigues(params[:, :3])
        pred = np.einsum("eij,ej->ei", R[j], self.nodes[k] - self.nodes[j]) + self.nodes[j] + params[j, 3:]
        energy = float(((pred - (self.nodes[k] + params[k, 3:])) ** 2).sum())
        return energy + rotation_weight * self.sigma ** 2 * float(((R[j] - R[k]) ** 2).sum())

    def to_dict(self) -> dict:
        return {"nodes": self.nodes.tolist(), "edges": self.edges.tolist(), "sigma": self.sigma,
                "params": self.params.tolist(), "n_anchors": self.n_anchors}

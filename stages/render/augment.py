"""Temporal-misalignment augmentation: smooth random 2D deformations of one view.

Reads/writes nothing on disk. Real XA runs are not simultaneous, so the two views of a training pair
must not be perfectly consistent. :func:`random_warp` draws a thin-plate-spline (TPS) displacement
field over the image:

* ``n_ctrl × n_ctrl`` control points on a jittered regular grid covering the image (default 4×4);
* i.i.d. Gaussian displacements at the control points, then the TPS interpolant (kernel r² log r,
  exact at the control points, affine part included) is rescaled so that the displacement's
  root-mean-square over the whole image equals ``rms_px`` (default 2 px at 512², i.e. ≈ 0.5–0.7 mm at
  the isocentre for typical spacings: the size of the residual mismatch between phase-matched frames).

The warp is a *forward* map of image points: a pixel location ``x`` of the unwarped projection moves
to ``x + u(x)``. The renderer applies it to the projected mesh vertices before rasterising (the
triangles are ~1–2 px so the piecewise-linear warp of the silhouette is exact to well below a pixel),
and any point (a correspondence, a centreline node) maps through :meth:`Warp2D.apply` exactly the same
way. Parameters (control points, control displacements) travel with every training pair, so the warp
is reproducible from them alone (``Warp2D.from_params``).

The optional 3D augmentation (a different cardiac phase of the same tree for the second view) is done
by :mod:`stages.render.pairs` with :mod:`stages.render.motion`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Warp2D", "random_warp", "identity_warp"]


def _tps_kernel(r2: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        k = 0.5 * r2 * np.log(r2)  # r² log r = ½ r² log r²
    return np.nan_to_num(k, nan=0.0, posinf=0.0, neginf=0.0)


@dataclass
class Warp2D:
    """TPS displacement field defined by control points (K×2 row, col) and their displacements (K×2)."""

    ctrl: np.ndarray
    disp: np.ndarray
    scale: float = 1.0  # normalises coordinates (image size) for a well-conditioned solve

    def __post_init__(self):
        self.ctrl = np.asarray(self.ctrl, dtype=float).reshape(-1, 2)
        self.disp = np.asarray(self.disp, dtype=float).reshape(-1, 2)
        k = len(self.ctrl)
        if k == 0 or not np.any(self.disp):
            self._coef = None
            return
        c = self.ctrl / self.scale
        A = np.zeros((k + 3, k + 3))
        A[:k, :k] = _tps_kernel(((c[:, None, :] - c[None, :, :]) ** 2).sum(-1))
        P = np.hstack([np.ones((k, 1)), c])
        A[:k, k:] = P
        A[k:, :k] = P.T
        b = np.zeros((k + 3, 2))
        b[:k] = self.disp
        self._coef = np.linalg.solve(A, b)

    @property
    def is_identity(self) -> bool:
        return self._coef is None

    def displacement(self, rc) -> np.ndarray:
        """Displacement (N×2 px) at points (N×2 row, col)."""
        rc = np.asarray(rc, dtype=float)
        shape = rc.shape
        rc = rc.reshape(-1, 2)
        if self._coef is None:
            return np.zeros(shape)
        k = len(self.ctrl)
        p = rc / self.scale
        c = self.ctrl / self.scale
        U = _tps_kernel(((p[:, None, :] - c[None, :, :]) ** 2).sum(-1))
        out = U @ self._coef[:k] + self._coef[k] + p @ self._coef[k + 1:]
        return out.reshape(shape)

    def apply(self, rc) -> np.ndarray:
        """Warped positions x + u(x) of points (N×2 row, col); NaNs stay NaN."""
        rc = np.asarray(rc, dtype=float)
        return rc + np.nan_to_num(self.displacement(np.nan_to_num(rc)))

    def rms(self, rows: int, cols: int, n: int = 24) -> float:
        rr, cc = np.meshgrid(np.linspace(0, rows - 1, n), np.linspace(0, cols - 1, n), indexing="ij")
        d = self.displacement(np.stack([rr.ravel(), cc.ravel()], 1))
        return float(np.sqrt((d ** 2).sum(1).mean()))

    def params(self) -> np.ndarray:
        """K×4 array (ctrl row, ctrl col, disp row, disp col) — the stored deformation parameters."""
        return np.hstack([self.ctrl, self.disp])

    @classmethod
    def from_params(cls, params, scale: float = 1.0) -> "Warp2D":
        params = np.asarray(params, dtype=float).reshape(-1, 4)
        return cls(params[:, :2], params[:, 2:], scale)


def identity_warp(rows: int, cols: int) -> Warp2D:
    return Warp2D(np.zeros((0, 2)), np.zeros((0, 2)), float(max(rows, cols)))


def random_warp(rng: np.random.Generator, rows: int, cols: int, rms_px: float = 2.0, n_ctrl: int = 4) -> Warp2D:
    """A smooth random TPS warp whose RMS displacement over the image is ``rms_px`` pixels."""
    if rms_px <= 0:
        return identity_warp(rows, cols)
    g = np.linspace(0.0, 1.0, n_ctrl)
    gr, gc = np.meshgrid(g * (rows - 1), g * (cols - 1), indexing="ij")
    ctrl = np.stack([gr.ravel(), gc.ravel()], 1)
    ctrl = ctrl + rng.uniform(-0.2, 0.2, ctrl.shape) * np.array([rows, cols]) / max(n_ctrl - 1, 1)
    disp = rng.standard_normal(ctrl.shape)
    scale = float(max(rows, cols))
    w = Warp2D(ctrl, disp, scale)
    r = w.rms(rows, cols)
    return Warp2D(ctrl, disp * (rms_px / max(r, 1e-9)), scale)

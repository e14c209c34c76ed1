"""XA image formation: per-frame X-ray angiograms of a (moving) coronary lumen mesh.

Reads nothing from disk; returns frames as arrays. Physics, per pixel-centre ray (camera of
:mod:`stages.core.geometry`):

    N = N₀ · T_coll · exp(−(B_static + B_dynamic + μ_I · ∫ c dl + A_cath) + B_ref)

* ``∫ c dl`` — the iodine line integral through the lumen: path length inside the closed lumen mesh
  weighted by the local contrast concentration c ∈ [0, 1] (:func:`stages.render.raster.rasterise_path_length`),
  so stenoses (short chords), overlaps and foreshortened segments (long chords) look as in clinical
  images. ``μ_I`` (0.22–0.27 /mm for fully opacified lumen) sets vessel contrast.
* ``c`` — the contrast bolus: every centreline node gets the bolus curve (smooth rise over ``rise`` s,
  plateau, exponential wash-out with time constant ``washout_tau`` s after ``t_washout``) delayed by
  its path distance from the ostium divided by the flow speed, so the tree fills proximal→distal and
  washes out over the run; mesh faces take the concentration of their nearest node.
* ``B_static`` — background anatomy as analytic 3D line integrals (ray/ellipsoid chords) of a thorax:
  body, two lungs (negative: air), vertebral bodies and posterior elements stacked along z with disc
  gaps, and ribs (3D arcs splatted as Gaussian tubes). Views of the same patient are therefore
  consistent: in LAO the spine moves to the right, as in real runs. Plus a fixed lung/soft-tissue
  texture (band-limited noise).
* ``B_dynamic`` — per frame: the diaphragm/liver dome (moves with respiration) and the cardiac
  silhouette (an ellipsoid that contracts with the cardiac phase).
* ``A_cath`` — optionally a contrast-filled 6F catheter from the ostium up the ascending aorta and over
  the arch, its tip moving with the heart.
* ``T_coll`` — collimator: a rectangle with rounded (iris-cut) corners, soft edge, 3 % transmission
  outside.
* Quantum noise (Poisson on N; N₀ is given per pixel of a 512² image and scales with the pixel area
  at other sizes), then detector blur (Gaussian, σ 0.6–0.75 px at 512², which also correlates
  the noise as a scintillator does), then a log transform and window to ``bits`` (8–12) with vessels
  dark: value = mean_level + gain·(log N − median log N in the field of view).

:class:`XAScene` holds everything fixed for one run (camera, anatomy, noise level); :meth:`XAScene.frame`
renders one frame from a deformed mesh and the frame's concentration/phase/respiration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.geometry import Camera
from .raster import rasterise_path_length

__all__ = ["BolusModel", "XAScene", "XAStyle", "sample_style", "sample_varied_style", "bolus_concentration", "node_path_distance",
           "default_catheter_path"]


# ------------------------------------------------------------------------------------------ bolus
@dataclass
class BolusModel:
    t_start: float = 0.3  # s after the run's first frame when contrast reaches the ostium
    rise: float = 0.6  # s from 0 to full concentration
    t_washout: float = 3.0  # s: wash-out begins (at the ostium)
    washout_tau: float = 0.8  # s
    speed: float = 200.0  # mm/s contrast front speed along the tree

    def at(self, t) -> np.ndarray:
        """Concentration in [0, 1] at the ostium at time(s) t (s)."""
        t = np.asarray(t, dtype=float)
        x = np.clip((t - self.t_start) / self.rise, 0.0, 1.0)
        c = x * x * (3 - 2 * x)  # smoothstep
        return np.where(t > self.t_washout, c * np.exp(-(t - self.t_washout) / self.washout_tau), c)


def node_path_distance(nodes: np.ndarray, edges: np.ndarray, root: int | None = None) -> tuple[np.ndarray, int]:
    """Path distance (mm) of every centreline node from the root (ostium) along the tree edges.

    The root defaults to the endpoint of the largest-radius end... here: the degree-1 node farthest up
    the tree — the caller passes it when known; otherwise the node with the largest distance-sum
    heuristic is avoided and we take the degree-1 node nearest the tree's most superior point.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    nodes = np.asarray(nodes, float)
    edges = np.asarray(edges, int).reshape(-1, 2)
    n = len(nodes)
    w = np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1)
    g = coo_matrix((np.r_[w, w], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n))
    if root is None:
        deg = np.bincount(edges.ravel(), minlength=n)
        ends = np.flatnonzero(deg == 1)
        root = int(ends[np.argmax(nodes[ends, 2])]) if ends.size else 0
    d = dijkstra(g.tocsr(), indices=root)
    d[~np.isfinite(d)] = np.nanmax(d[np.isfinite(d)]) if np.isfinite(d).any() else 0.0
    return d, root


def bolus_concentration(bolus: BolusModel, t: float, node_dist: np.ndarray) -> np.ndarray:
    return bolus.at(t - node_dist / bolus.speed)


# ------------------------------------------------------------------------------------------ style
@dataclass
class XAStyle:
    """Per-run imaging parameters (all drawn by :func:`sample_style`)."""

    photons: float = 100.0  # mean detected quanta per pixel (of a 512² image) at the reference attenuation
    mu_iodine: float = 0.245  # 1/mm, fully opacified lumen
    blur_px: float = 0.68  # detector blur σ in pixels (at 512²; scaled with image size)
    gain: float = 160.0  # grey levels (8-bit scale) per unit of log intensity
    anatomy: float = 0.055  # scale of the background anatomy's attenuation (patient size / kV)
    harmonise: float = 0.86  # fraction of the low-frequency log-intensity removed (clinical harmonisation)
    mean_level: float = 105.0  # grey level (8-bit scale) of the median field-of-view intensity
    texture: float = 0.009  # amplitude of the lung/soft-tissue texture (log units)
    catheter: bool = True
    collimator_margin: float = 0.02  # fraction of the image width hidden by each shutter blade
    collimator_corner: float = 0.63  # iris radius as a fraction of the image width
    bits: int = 8


def sample_style(rng: np.random.Generator, bits: int = 8, catheter: bool | None = None) -> XAStyle:
    """A random run style. The ranges put vessel CNR, pixel noise and background mean/std of the
    simulated runs in the range of the real phantom runs (docs/SIMULATION.md §6): faint anatomy after
    strong harmonisation, quanta and iodine attenuation such that vessels stand 11–15 σ above the noise."""
    return XAStyle(
        photons=float(rng.uniform(85, 120)), mu_iodine=float(rng.uniform(0.22, 0.27)),
        blur_px=float(rng.uniform(0.6, 0.75)), gain=float(rng.uniform(150, 170)),
        anatomy=float(rng.uniform(0.045, 0.065)), harmonise=float(rng.uniform(0.82, 0.9)),
        mean_level=float(rng.uniform(102, 107)), texture=float(rng.uniform(0.006, 0.012)),
        catheter=bool(rng.random() < 0.8) if catheter is None else catheter,
        collimator_margin=float(rng.uniform(0.0, 0.03)), collimator_corner=float(rng.uniform(0.6, 0.67)),
        bits=bits,
    )


def sample_varied_style(rng: np.random.Generator, catheter: bool | None = None) -> XAStyle:
    """:func:`sample_style` widened the way the 2D segmenter's training frames are: a quarter of the runs
    phantom-like (faint anatomy, smooth background) and the dose over a wider range (0.6–2.5×)."""
    style = sample_style(rng, bits=8, catheter=catheter)
    if rng.random() < 0.25:
        style.anatomy *= 0.15
        style.texture *= 0.3
    style.photons *= float(rng.uniform(0.6, 2.5))
    return style


# ------------------------------------------------------------------------------------------ maths
def _pixel_rays(camera: Camera) -> np.ndarray:
    """H×W×3 unit ray directions through the pixel centres."""
    rr, cc = np.meshgrid(np.arange(camera.rows, dtype=float), np.arange(camera.cols, dtype=float), indexing="ij")
    _, d = camera.rays(np.stack([rr.ravel(), cc.ravel()], 1))
    return d.reshape(camera.rows, camera.cols, 3)


def _ellipsoid_chord(source, dirs, centre, semi, axes=None) -> np.ndarray:
    """Chord length (mm) of every ray (source + t·dir) through an ellipsoid."""
    R = np.eye(3) if axes is None else np.asarray(axes, float)
    s = np.asarray(semi, float)
    o = (R @ (np.asarray(source, float) - np.asarray(centre, float))) / s
    d = (dirs @ R.T) / s
    a = np.einsum("...k,...k->...", d, d)
    b = 2.0 * (d @ o)
    c = o @ o - 1.0
    disc = b * b - 4 * a * c
    return np.sqrt(np.maximum(disc, 0.0)) / a


def _splat_tubes(camera: Camera, points: np.ndarray, weight: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Line integral image of Gaussian tubes through ``points`` (sampled ~1 mm apart, weight = μ·area·ds)."""
    from scipy import ndimage

    rc, depth = camera.project(points, return_depth=True)
    ok = np.all(np.isfinite(rc), 1)
    rc, weight = rc[ok], weight[ok]
    H, W = camera.rows, camera.cols
    sp = camera.isocentre_spacing
    img = np.zeros((H + 2, W + 2))
    r0 = np.floor(rc[:, 0]).astype(int)
    c0 = np.floor(rc[:, 1]).astype(int)
    fr, fc = rc[:, 0] - r0, rc[:, 1] - c0
    for dr, dc, wgt in ((0, 0, (1 - fr) * (1 - fc)), (1, 0, fr * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 1, fr * fc)):
        rr, cc = r0 + dr + 1, c0 + dc + 1
        inb = (rr >= 0) & (rr < H + 2) & (cc >= 0) & (cc < W + 2)
        np.add.at(img, (rr[inb], cc[inb]), weight[inb] * wgt[inb])
    img = img[1:-1, 1:-1] / (sp * sp)
    return ndimage.gaussian_filter(img, sigma_mm / sp, mode="constant")


def _texture(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """Band-limited 1/f-like noise, zero mean, unit std."""
    from scipy import ndimage

    out = np.zeros((H, W))
    for sigma, amp in ((2.0, 0.5), (6.0, 1.0), (16.0, 1.0), (40.0, 0.8)):
        n = ndimage.gaussian_filter(rng.standard_normal((H, W)), sigma * max(H, W) / 512)
        out += amp * n / (n.std() + 1e-12)
    return (out - out.mean()) / (out.std() + 1e-12)


def _lowpass(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass (σ in pixels, zero outside the image) computed on a block-averaged grid.

    For the wide kernels of the harmonisation (σ ≈ 40 px) a block of f = σ // 10 pixels is far below the
    kernel's scale, so averaging f×f blocks, filtering with σ/f and interpolating back (bilinear, block
    centres aligned) matches the full-resolution filter to a small fraction of a grey level, for
    about 1/f² of the work.
    """
    from scipy import ndimage

    f = max(1, int(sigma // 10))
    if f == 1:
        return ndimage.gaussian_filter(img, sigma, mode="constant")
    H, W = img.shape
    Hp, Wp = -(-H // f) * f, -(-W // f) * f
    pad = np.zeros((Hp, Wp))
    pad[:H, :W] = img
    small = pad.reshape(Hp // f, f, Wp // f, f).mean(axis=(1, 3))
    small = ndimage.gaussian_filter(small, sigma / f, mode="constant")
    return ndimage.zoom(small, f, order=1, grid_mode=True, mode="nearest")[:H, :W]


def _collimator(H: int, W: int, margin: float, corner: float) -> np.ndarray:
    """Transmission of the collimator (shutters + iris): 1 inside, 0.03 outside, soft edge."""
    from scipy import ndimage

    rr, cc = np.meshgrid((np.arange(H) - (H - 1) / 2) / W, (np.arange(W) - (W - 1) / 2) / W, indexing="ij")
    half = 0.5 - margin
    inside = (np.abs(rr) <= half * H / W) & (np.abs(cc) <= half) & (np.hypot(rr, cc) <= corner)
    soft = ndimage.gaussian_filter(inside.astype(float), 1.5 * W / 512)
    return 0.03 + 0.97 * soft


# ------------------------------------------------------------------------------------------ scene
@dataclass
class XAScene:
    """Everything fixed during one run: camera, anatomy layout, imaging style and the noise seed."""

    camera: Camera
    style: XAStyle
    heart_centre: np.ndarray
    heart_axis: np.ndarray
    seed: int
    catheter_path: np.ndarray | None = None  # M×3 reference-configuration catheter centreline (ostium first)
    diaphragm_z: float = -70.0  # dome top at end-expiration (mm, relative to the heart centre)
    anatomy_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        cam = self.camera
        self._dirs = _pixel_rays(cam)
        self._rng = np.random.default_rng(self.seed)
        self._static = self._static_background()
        self._texture = self.style.texture * _texture(np.random.default_rng(self.seed + 1), cam.rows, cam.cols)
        self._coll = _collimator(cam.rows, cam.cols, self.style.collimator_margin, self.style.collimator_corner)
        self._open_field = self._coll > 0.5
        # the harmonisation's normalised low-pass divides by the smoothed open field: fixed for the run
        self._open_norm = np.maximum(_lowpass(self._open_field.astype(float), 40 * max(cam.rows, cam.cols) / 512.0), 1e-3)
        self._ref_level = None

    @property
    def open_field(self) -> np.ndarray:
        """H×W bool: pixels the collimator lets through (transmission > ½); outside, nothing is visible."""
        return self._open_field

    # ---------------------------------------------------------------- anatomy
    def _static_background(self) -> np.ndarray:
        cam, S, D = self.camera, self.camera.source, self._dirs
        sh = self.anatomy_shift
        B = 0.02 * _ellipsoid_chord(S, D, sh + [0, 30, 0], [165, 115, 420])  # body (water)
        for side in (-1, 1):  # lungs: air where tissue would be
            B -= 0.017 * _ellipsoid_chord(S, D, sh + [side * 85, 25, 40], [62, 80, 120])
        B += 0.004 * _ellipsoid_chord(S, D, sh + [0, 15, 30], [40, 40, 140])  # mediastinum
        for z in np.arange(-240, 241, 30.0):  # vertebrae: body + posterior elements, discs between
            B += 0.03 * _ellipsoid_chord(S, D, sh + [0, 85, z], [22, 17, 12])
            B += 0.02 * _ellipsoid_chord(S, D, sh + [0, 118, z - 4], [30, 10, 8])
        # ribs: arcs from the spine round the chest wall, descending anteriorly
        pts, w = [], []
        for z0 in np.arange(-150, 181, 28.0):
            for side in (-1, 1):
                th = np.linspace(0.08 * np.pi, 0.82 * np.pi, 220)
                x = side * 148 * np.sin(th)
                y = 30 + 108 * np.cos(th)
                z = z0 - 55 * th / np.pi
                p = np.stack([x, y, z], 1) + sh
                ds = np.linalg.norm(np.diff(p, axis=0), axis=1).mean()
                pts.append(p)
                w.append(np.full(len(p), 0.04 * np.pi * 4.0 ** 2 * ds))  # bone μ · cross-section · ds
        B += _splat_tubes(cam, np.concatenate(pts), np.concatenate(w), 3.0)
        return B

    def _dynamic_background(self, phase_contraction: float, resp: float, resp_vector) -> np.ndarray:
        S, D = self.camera.source, self._dirs
        sh = self.anatomy_shift + 1.5 * resp * np.asarray(resp_vector, float)
        c = self.heart_centre
        B = np.zeros(D.shape[:2])
        # diaphragm domes: liver (right, −x) and stomach/spleen side (left), replacing lung
        B += 0.019 * _ellipsoid_chord(S, D, sh + [c[0] - 45, 20, c[2] + self.diaphragm_z - 95], [120, 95, 95])
        B += 0.017 * _ellipsoid_chord(S, D, sh + [c[0] + 55, 20, c[2] + self.diaphragm_z - 115], [90, 85, 95])
        # cardiac silhouette: ellipsoid along the long axis, contracting
        u = self.heart_axis / np.linalg.norm(self.heart_axis)
        v = np.cross(u, [0.0, 0.0, 1.0])
        v = v / (np.linalg.norm(v) + 1e-12)
        w = np.cross(u, v)
        k = 1.0 - 0.1 * phase_contraction
        B += 0.006 * _ellipsoid_chord(S, D, c + 1.0 * resp * np.asarray(resp_vector, float),
                                      [62 * k, 52 * k, 52 * k], np.stack([u, v, w]))
        return B

    def _catheter(self, path_now: np.ndarray) -> np.ndarray:
        # resample to ~0.5 mm
        seg = np.linalg.norm(np.diff(path_now, axis=0), axis=1)
        s = np.concatenate([[0], np.cumsum(seg)])
        t = np.arange(0, s[-1], 0.5)
        p = np.stack([np.interp(t, s, path_now[:, k]) for k in range(3)], 1)
        r_cath = 1.0
        # contrast-filled catheter (iodine) plus its wall
        w = np.full(len(p), (self.style.mu_iodine * 0.8 + 0.01) * np.pi * r_cath ** 2 * 0.5)
        return _splat_tubes(self.camera, p, w, r_cath * 0.6)

    # ---------------------------------------------------------------- frames
    def frame(self, vertices, faces, face_conc, contraction_s: float = 0.0, resp: float = 0.0,
              resp_vector=(0, 0, 0), catheter_now: np.ndarray | None = None, frame_index: int = 0,
              rng: np.random.Generator | None = None, path_length: np.ndarray | None = None) -> np.ndarray:
        """One frame as float64 grey values (8-bit scale before quantisation) — see :meth:`quantise`.

        ``path_length``: the frame's concentration-weighted lumen path length when the caller already
        rasterised it (:func:`stages.render.raster.rasterise_lumen`); otherwise it is computed here.
        """
        from scipy import ndimage

        st = self.style
        cam = self.camera
        if path_length is None:
            path_length = rasterise_path_length(vertices, faces, cam, face_weight=face_conc)
        L = path_length
        A = st.anatomy * (self._static + self._dynamic_background(contraction_s, resp, resp_vector)) + self._texture
        A = A + st.mu_iodine * L
        if st.catheter and catheter_now is not None:
            A = A + self._catheter(catheter_now)
        if self._ref_level is None:
            # reference attenuation: the median over the open field, fixed for the run
            self._ref_level = float(np.median(A[self._coll > 0.9]))
        # blur and quanta are set for a 512² image of the detector: a coarser matrix has larger pixels,
        # so a narrower blur in pixels and more quanta per pixel (∝ pixel area, same dose)
        scale = max(cam.rows, cam.cols) / 512.0
        n0 = st.photons / (scale * scale)
        expected = n0 * self._coll * np.exp(-(A - self._ref_level))
        rng = rng or np.random.default_rng((self.seed, frame_index))
        counts = rng.poisson(np.clip(expected, 0, None)).astype(float)
        counts = ndimage.gaussian_filter(counts, st.blur_px * scale)
        logn = np.log(np.maximum(counts, 0.5) / n0)
        # harmonisation (unsharp masking of the log image), as clinical XA processing does: it keeps
        # the background grey across lung, heart and spine while leaving vessel contrast untouched
        open_field = self._open_field
        low = _lowpass(np.where(open_field, logn, 0.0), 40 * scale) / self._open_norm
        logn = np.where(open_field, logn - st.harmonise * (low - np.median(logn[open_field])), logn)
        return st.mean_level + st.gain * logn

    def quantise(self, grey: np.ndarray) -> np.ndarray:
        """8-bit-scale grey values → unsigned integers at ``style.bits``."""
        top = 2 ** self.style.bits - 1
        v = np.clip(np.rint(grey * top / 255.0), 0, top)
        return v.astype(np.uint8 if self.style.bits <= 8 else np.uint16)


def default_catheter_path(ostium: np.ndarray, heart_centre: np.ndarray, heart_axis: np.ndarray,
                          rng: np.random.Generator) -> np.ndarray:
    """A plausible catheter course (reference configuration): ostium → aortic root → ascending aorta →
    arch → descending aorta, as a smooth polyline (mm, LPS), ostium first."""
    from scipy.interpolate import CubicSpline

    u = np.asarray(heart_axis, float) / np.linalg.norm(heart_axis)
    o = np.asarray(ostium, float)
    root = o - 12.0 * u + np.array([-8.0, 5.0, 0.0])  # back towards the base / aortic root
    asc = np.array([heart_centre[0] - 25.0, heart_centre[1] + 5.0, o[2] + 70.0])
    arch_top = np.array([heart_centre[0] - 5.0, heart_centre[1] + 35.0, o[2] + 110.0])
    arch_back = np.array([heart_centre[0] + 20.0, heart_centre[1] + 65.0, o[2] + 95.0])
    desc = np.array([heart_centre[0] + 22.0, heart_centre[1] + 70.0, o[2] - 250.0])
    ctrl = np.stack([o, root, asc, arch_top, arch_back, desc]) + rng.normal(0, 3.0, (6, 3)) * np.array([[0], [1], [1], [1], [1], [1]])
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(ctrl, axis=0), axis=1))])
    cs = CubicSpline(s, ctrl, axis=0)
    return cs(np.arange(0, s[-1], 1.0))

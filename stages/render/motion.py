"""Dynamic heart model: periodic non-rigid motion of a coronary tree plus respiratory translation.

Reads nothing from disk; acts on world points (mesh vertices, centreline nodes, truth points, mm, LPS).
The reference configuration is the prepared case as stored (taken as end-diastole, cardiac phase 0).

Model (all parameters in :class:`HeartMotion`, JSON-serialisable via ``to_dict``/``from_dict`` so a
sidecar artefact can reproduce every frame's geometry exactly):

* A heart frame: centre ``c`` and unit long axis ``u`` (base → apex). A point ``p`` has axial
  coordinate ``a = (p − c)·u`` and radial vector ``q = (p − c) − a·u``.
* A contraction curve ``s(φ)`` in [0, 1] over the cardiac phase φ ∈ [0, 1): 0 at end-diastole (φ = 0),
  rising with a half-cosine to 1 at end-systole (φ = ``t_systole``), relaxing with a half-cosine over
  ``t_relax`` and then flat (diastasis) until the next beat. The curve is C¹ (zero slope at the joins).
* At contraction ``s``:
  - radial contraction: ``q ← q · (1 − radial · s)`` (``radial`` ≈ 0.10–0.15),
  - long-axis shortening towards the apex: ``a ← a_apex + (a − a_apex)(1 − axial · s)``, the base
    descends towards a nearly fixed apex as in a real ventricle (``axial`` ≈ 0.10–0.15),
  - twist about ``u``: angle ``twist · s · (ā − ½)`` with ``ā`` the point's normalised axial position
    between base (0) and apex (1), so base and apex turn in opposite senses and differ by
    ``twist`` degrees at end-systole (≈ 5–10°).
* Respiration adds a rigid translation ``resp · resp_vector`` (``resp`` ∈ [0, 1] from
  :meth:`HeartMotion.resp_state`: 0 at end-expiration); ``resp_vector`` is mostly cranio-caudal
  (up to ~10 mm) or zero for a breath-hold.

Time: :meth:`HeartMotion.phase_at` maps acquisition time (s) to cardiac phase through a sequence of
RR intervals with beat-to-beat variation (heart rate 50–100 bpm); :meth:`resp_state` is a raised
cosine of the breathing period.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["HeartMotion", "contraction", "heart_frame", "heart_frame_from_points", "sample_motion"]


def contraction(phase, t_systole: float = 0.35, t_relax: float = 0.2):
    """Contraction s(φ) ∈ [0, 1]; φ is taken modulo 1."""
    phi = np.mod(np.asarray(phase, dtype=float), 1.0)
    s = np.zeros_like(phi)
    up = phi < t_systole
    s[up] = 0.5 * (1.0 - np.cos(np.pi * phi[up] / t_systole))
    down = (phi >= t_systole) & (phi < t_systole + t_relax)
    s[down] = 0.5 * (1.0 + np.cos(np.pi * (phi[down] - t_systole) / t_relax))
    return s


def heart_frame_from_points(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate (centre, long axis) from a tree's points by PCA when a case has no ``heart`` attrs.

    The long axis is the principal direction, signed to point anterior-inferior-left (apex direction
    of a supine heart: −y, −z, +x in LPS).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    axis = vt[0]
    if axis @ np.array([1.0, -1.0, -1.0]) < 0:
        axis = -axis
    return centre, axis / np.linalg.norm(axis)


def heart_frame(points: np.ndarray, heart: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(centre, unit long axis) of a tree's heart: from ``heart`` attrs (centre, long_axis) when given,
    else estimated from the tree's points (:func:`heart_frame_from_points`)."""
    if heart and "centre" in heart and "long_axis" in heart:
        axis = np.asarray(heart["long_axis"], float)
        return np.asarray(heart["centre"], float), axis / np.linalg.norm(axis)
    return heart_frame_from_points(np.asarray(points, dtype=float).reshape(-1, 3))


@dataclass
class HeartMotion:
    centre: list  # (3,) mm
    long_axis: list  # (3,) unit, base → apex
    axial_range: list  # [a_base, a_apex] axial coordinates (mm) spanning the tree
    radial: float = 0.12
    axial: float = 0.12
    twist_deg: float = 7.0
    t_systole: float = 0.35
    t_relax: float = 0.2
    heart_rate_bpm: float = 70.0
    rr_jitter: float = 0.04  # relative std of RR intervals (beat-to-beat variation)
    rr_intervals: list = field(default_factory=list)  # s, one per beat from t = 0
    phase0: float = 0.0  # cardiac phase at t = 0
    resp_vector: list = field(default_factory=lambda: [0.0, 0.0, 0.0])  # mm at full inspiration
    resp_period: float = 4.0  # s
    resp_phase0: float = 0.0  # breathing phase at t = 0, in [0, 1)

    # ------------------------------------------------------------------ construction
    @classmethod
    def for_points(cls, points, heart: dict | None = None, **kwargs) -> "HeartMotion":
        """Build the model around a tree: heart frame from ``heart`` attrs (centre, long_axis) or PCA."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        centre, axis = heart_frame(pts, heart)
        a = (pts - centre) @ axis
        return cls(centre=centre.tolist(), long_axis=axis.tolist(),
                   axial_range=[float(a.min()), float(a.max())], **kwargs)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "HeartMotion":
        return cls(**d)

    # ------------------------------------------------------------------ time
    def _ensure_beats(self, t_max: float) -> np.ndarray:
        rr = np.asarray(self.rr_intervals, float)
        if rr.size == 0 or rr.sum() < t_max + 1.0:
            raise ValueError("rr_intervals do not cover the requested time; build with sample_motion(duration=...)")
        return rr

    def phase_at(self, t) -> np.ndarray:
        """Cardiac phase in [0, 1) at times ``t`` (s since the model's t = 0)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        rr = self._ensure_beats(float(t.max()) if t.size else 0.0)
        # phase0 shifts the start inside the first beat
        t_eff = t + self.phase0 * rr[0]
        starts = np.concatenate([[0.0], np.cumsum(rr)])
        k = np.clip(np.searchsorted(starts, t_eff, side="right") - 1, 0, len(rr) - 1)
        return np.mod((t_eff - starts[k]) / rr[k], 1.0)

    def resp_state(self, t) -> np.ndarray:
        """Respiratory state in [0, 1] at times ``t``: 0 end-expiration, 1 full inspiration."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return 0.5 * (1.0 - np.cos(2 * np.pi * (t / self.resp_period + self.resp_phase0)))

    # ------------------------------------------------------------------ deformation
    def apply(self, points, phase: float, resp: float = 0.0) -> np.ndarray:
        """Positions of reference-configuration points at cardiac ``phase`` and respiratory state ``resp``."""
        p = np.asarray(points, dtype=float)
        shape = p.shape
        p = p.reshape(-1, 3)
        c = np.asarray(self.centre, float)
        u = np.asarray(self.long_axis, float)
        s = float(contraction(phase, self.t_systole, self.t_relax))
        d = p - c
        a = d @ u
        q = d - a[:, None] * u
        a_base, a_apex = self.axial_range
        span = max(a_apex - a_base, 1e-6)
        # contraction and shortening (towards the apex)
        q = q * (1.0 - self.radial * s)
        a_new = a_apex + (a - a_apex) * (1.0 - self.axial * s)
        # twist about u, linear in normalised axial position
        abar = np.clip((a - a_base) / span, 0.0, 1.0)
        theta = np.radians(self.twist_deg) * s * (abar - 0.5)
        ct, st = np.cos(theta)[:, None], np.sin(theta)[:, None]
        # Rodrigues (q ⟂ u); u × q as q @ [u]ₓᵀ, cheaper than np.cross on the ~10⁶ vertices of a frame
        cross_u = np.array([[0.0, u[2], -u[1]], [-u[2], 0.0, u[0]], [u[1], -u[0], 0.0]])
        q = q * ct + (q @ cross_u) * st
        out = c + a_new[:, None] * u + q
        out = out + float(resp) * np.asarray(self.resp_vector, float)
        return out.reshape(shape)

    def at_time(self, points, t: float) -> np.ndarray:
        return self.apply(points, float(self.phase_at(t)[0]), float(self.resp_state(t)[0]))


def sample_motion(points, rng: np.random.Generator, heart: dict | None = None, duration: float = 10.0,
                  breath_hold: bool | None = None) -> HeartMotion:
    """Draw a random heart: rate 50–100 bpm, radial/axial 10–15 %, twist 5–10°, respiration ≤ 10 mm or breath-hold.

    ``duration`` (s) is how long the RR sequence must cover (two runs one after the other and a gap).
    """
    hr = float(rng.uniform(50, 100))
    jitter = float(rng.uniform(0.02, 0.06))
    n_beats = int(math.ceil((duration + 2.0) * hr / 60.0 * 1.5)) + 2
    rr = 60.0 / hr * np.clip(1.0 + jitter * rng.standard_normal(n_beats), 0.8, 1.2)
    if breath_hold is None:
        breath_hold = bool(rng.random() < 0.4)
    if breath_hold:
        resp_vec = [0.0, 0.0, 0.0]
    else:
        amp = float(rng.uniform(3.0, 10.0))
        # inspiration moves the heart caudally (−z) with a small anterior component (−y)
        resp_vec = (amp * np.array([0.0, -0.25, -1.0]) / np.linalg.norm([0.0, -0.25, -1.0])).tolist()
    return HeartMotion.for_points(
        points, heart,
        radial=float(rng.uniform(0.10, 0.15)), axial=float(rng.uniform(0.10, 0.15)),
        twist_deg=float(rng.uniform(5.0, 10.0)), t_systole=float(rng.uniform(0.30, 0.38)),
        t_relax=float(rng.uniform(0.15, 0.25)), heart_rate_bpm=hr, rr_jitter=jitter,
        rr_intervals=rr.tolist(), phase0=float(rng.uniform(0, 1)), resp_vector=resp_vec,
        resp_period=float(rng.uniform(3.5, 5.5)), resp_phase0=float(rng.uniform(0, 1)),
    )

"""Stage ``fit-poses``: C-arm pose statistics for pose-domain adaptation.

Reads: a folder of XA DICOM runs (recursively), or nothing (``--default``, the built-in model).
Writes: a pose-model artefact (zarr, kind ``autocar.pose-model``) holding every recorded pose
(α, β, SID, SOD, detector spacing, image size) with its K-means cluster label and the cluster
centres, plus a PNG figure beside it (α/β scatter by cluster, SID/SOD/spacing histograms).

Sampling (the paper's pose-domain adaptation): draw two *distinct* clusters, uniformly by default,
then one recorded pose from each — all parameters of a pose together, never independent draws of
SID/SOD/spacing. A model built with ``sampling="independent"`` (the uniform-sphere ablation, L7)
draws both poses from the whole set instead.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .core.artefacts import read_zarr, write_zarr
from .core.dicom_io import iter_dicom_files, read_xa
from .core.errors import UserError
from .core.figures import save_png
from .core.geometry import Camera

log = logging.getLogger(__name__)

POSE_MODEL_KIND = "autocar.pose-model"
POSE_MODEL_SCHEMA = 1

_FIELDS = ("alpha", "beta", "sid", "sod", "spacing_row", "spacing_col", "rows", "cols")

# The built-in model: standard coronary projections (α = LAO+/RAO−, β = CRA+/CAU−), in degrees.
STANDARD_VIEWS = {
    "AP cranial": (0.0, 30.0),
    "AP caudal": (0.0, -30.0),
    "RAO caudal": (-30.0, -25.0),
    "RAO cranial": (-30.0, 30.0),
    "LAO cranial": (45.0, 25.0),
    "LAO caudal (spider)": (45.0, -30.0),
    "RAO": (-30.0, 0.0),
    "LAO": (45.0, 0.0),
    "left lateral": (90.0, 0.0),
}


@dataclass(frozen=True)
class Pose:
    """One C-arm acquisition geometry (degrees, mm); ``cluster`` is its label in the model."""

    alpha: float
    beta: float
    sid: float
    sod: float
    spacing: tuple[float, float]
    rows: int
    cols: int
    cluster: int = -1

    def camera(self, rows: int | None = None, cols: int | None = None) -> Camera:
        """Camera of this pose; another image size keeps the detector's physical extent."""
        r, c = rows or self.rows, cols or self.cols
        spacing = (self.spacing[0] * self.rows / r, self.spacing[1] * self.cols / c)
        return Camera.from_carm(self.alpha, self.beta, self.sid, self.sod, spacing, r, c)

    def as_dict(self) -> dict:
        return {"alpha": self.alpha, "beta": self.beta, "sid": self.sid, "sod": self.sod,
                "spacing": list(self.spacing), "rows": self.rows, "cols": self.cols, "cluster": self.cluster}


def pose_to_camera(pose: Pose, rows: int | None = None, cols: int | None = None) -> Camera:
    return pose.camera(rows, cols)


@dataclass
class PoseModel:
    """Recorded poses (one row each) with cluster labels, and how pairs are drawn from them."""

    table: dict[str, np.ndarray]  # _FIELDS → (N,) arrays
    labels: np.ndarray  # (N,) int cluster label
    centres: np.ndarray  # (k, 2) α, β of each cluster centre
    cluster_names: list[str]
    cluster_probabilities: np.ndarray  # (k,) probability of drawing each cluster (uniform: the paper)
    sampling: str = "clusters"  # or "independent"
    sources: list[str] | None = None

    @property
    def n_clusters(self) -> int:
        return len(self.centres)

    def __len__(self) -> int:
        return len(self.labels)

    def pose(self, i: int) -> Pose:
        t = self.table
        return Pose(float(t["alpha"][i]), float(t["beta"][i]), float(t["sid"][i]), float(t["sod"][i]),
                    (float(t["spacing_row"][i]), float(t["spacing_col"][i])), int(t["rows"][i]), int(t["cols"][i]),
                    int(self.labels[i]))

    # ------------------------------------------------------------------ sampling
    def sample_pair(self, rng: np.random.Generator) -> tuple[Pose, Pose]:
        """Two poses the paper's way: two distinct clusters, then one recorded pose from each."""
        if self.sampling == "independent":
            i, j = rng.choice(len(self), size=2, replace=False)
            return self.pose(int(i)), self.pose(int(j))
        ca, cb = rng.choice(self.n_clusters, size=2, replace=False, p=self.cluster_probabilities)
        members_a = np.flatnonzero(self.labels == ca)
        members_b = np.flatnonzero(self.labels == cb)
        return self.pose(int(rng.choice(members_a))), self.pose(int(rng.choice(members_b)))

    def sample_other(self, rng: np.random.Generator, exclude_clusters=()) -> Pose:
        """One recorded pose from a cluster other than ``exclude_clusters`` (a further run of a study, taken
        from another standard angle); any cluster when no other one is left."""
        allowed = np.array([c not in set(exclude_clusters) for c in range(self.n_clusters)])
        if self.sampling == "independent" or not allowed.any():
            return self.pose(int(rng.integers(len(self))))
        p = np.asarray(self.cluster_probabilities, float) * allowed
        c = int(rng.choice(self.n_clusters, p=p / p.sum()))
        return self.pose(int(rng.choice(np.flatnonzero(self.labels == c))))

    # ------------------------------------------------------------------ construction
    @classmethod
    def fit(cls, poses: list[dict], n_clusters: int, seed: int = 0, sources=None) -> "PoseModel":
        """K-means on (α, β) of recorded poses."""
        from sklearn.cluster import KMeans

        if len(poses) < n_clusters:
            raise UserError(f"only {len(poses)} usable run(s) for {n_clusters} clusters; lower --clusters or add runs")
        table = {f: np.array([p[f] for p in poses], dtype=float) for f in _FIELDS}
        ab = np.stack([table["alpha"], table["beta"]], axis=1)
        if len(np.unique(ab, axis=0)) < n_clusters:
            raise UserError(f"only {len(np.unique(ab, axis=0))} distinct (α, β) poses for {n_clusters} clusters; lower --clusters")
        km = KMeans(n_clusters=n_clusters, n_init=10, random_state=seed).fit(ab)
        labels, centres = km.labels_.astype(np.int32), km.cluster_centers_
        # order clusters by α then β so labels are stable and readable
        order = np.lexsort((centres[:, 1], centres[:, 0]))
        remap = np.empty_like(order)
        remap[order] = np.arange(n_clusters)
        labels, centres = remap[labels].astype(np.int32), centres[order]
        names = [f"{_view_name(a, b)}" for a, b in centres]
        return cls(table, labels, centres, names, np.full(n_clusters, 1.0 / n_clusters), "clusters", sources)

    @classmethod
    def default(cls, seed: int = 0, per_cluster: int = 200) -> "PoseModel":
        """The built-in clinical model: nine standard projections, ~8° spread, joint SID/SOD/spacing.

        SID ~ U(900, 1200) mm; SOD follows SID (a longer SID is mostly a raised detector, the source
        moves less): with t = (SID−900)/300, SOD = 700 + 100·Beta(2 + 4t, 6 − 4t) mm, so SOD stays in
        700–800 mm, rises with SID, and SOD < SID always.
        Detector spacing: 0.19 mm + Gamma(k 2.5, θ 0.038 mm), clipped to 0.6 mm (median ≈ 0.27 mm,
        right-skewed) — most systems bin a ~0.15–0.2 mm flat panel to 0.25–0.37 mm for 512² cine, a few
        zoom out further (the heavier upper tail).
        Images 512×512.
        """
        rng = np.random.default_rng(seed)
        alphas, betas, labels = [], [], []
        for k, (a, b) in enumerate(STANDARD_VIEWS.values()):
            alphas.append(rng.normal(a, 8.0, per_cluster))
            betas.append(np.clip(rng.normal(b, 8.0, per_cluster), -60, 60))
            labels.append(np.full(per_cluster, k))
        n = per_cluster * len(STANDARD_VIEWS)
        sid = rng.uniform(900.0, 1200.0, n)
        t = (sid - 900.0) / 300.0
        sod = 700.0 + 100.0 * rng.beta(2.0 + 4.0 * t, 6.0 - 4.0 * t)
        spacing = np.minimum(0.19 + rng.gamma(2.5, 0.038, n), 0.6)
        table = {"alpha": np.concatenate(alphas), "beta": np.concatenate(betas), "sid": sid, "sod": sod,
                 "spacing_row": spacing, "spacing_col": spacing.copy(),
                 "rows": np.full(n, 512.0), "cols": np.full(n, 512.0)}
        centres = np.array(list(STANDARD_VIEWS.values()))
        k = len(centres)
        return cls(table, np.concatenate(labels).astype(np.int32), centres, list(STANDARD_VIEWS), np.full(k, 1.0 / k),
                   "clusters", ["built-in default"])

    @classmethod
    def uniform_sphere(cls, seed: int = 0, n: int = 1800, max_beta: float = 60.0) -> "PoseModel":
        """Ablation (paper L7): view directions uniform on the sphere (|β| ≤ max_beta for a C-arm),
        SID/SOD/spacing as in the default model, pairs drawn independently (no clusters)."""
        base = cls.default(seed=seed, per_cluster=max(1, n // len(STANDARD_VIEWS)))
        rng = np.random.default_rng(seed + 1)
        m = len(base)
        alpha = rng.uniform(-180.0, 180.0, m)
        limit = np.sin(np.radians(max_beta))
        beta = np.degrees(np.arcsin(rng.uniform(-limit, limit, m)))  # uniform in sin β = uniform area
        base.table["alpha"], base.table["beta"] = alpha, beta
        return cls(base.table, np.zeros(m, np.int32), np.zeros((1, 2)), ["uniform sphere"], np.ones(1),
                   "independent", ["built-in uniform sphere"])

    # ------------------------------------------------------------------ storage
    def save(self, path, stage: str = "fit-poses", inputs=(), parameters=None) -> Path:
        with write_zarr(path, kind=POSE_MODEL_KIND, schema_version=POSE_MODEL_SCHEMA, stage=stage,
                        inputs=inputs, parameters=parameters,
                        extra_attrs={"cluster_names": self.cluster_names, "sampling": self.sampling,
                                     "sources": self.sources or []}) as g:
            for f in _FIELDS:
                g.create_array(f, data=self.table[f].astype(np.float64))
            g.create_array("label", data=self.labels.astype(np.int32))
            g.create_array("centres", data=self.centres.astype(np.float64))
            g.create_array("cluster_probabilities", data=self.cluster_probabilities.astype(np.float64))
        return Path(path)

    @classmethod
    def load(cls, path) -> "PoseModel":
        g = read_zarr(path, kind=POSE_MODEL_KIND, schema_version=POSE_MODEL_SCHEMA)
        attrs = dict(g.attrs)
        return cls({f: g[f][...] for f in _FIELDS}, g["label"][...], g["centres"][...], list(attrs["cluster_names"]),
                   g["cluster_probabilities"][...], attrs.get("sampling", "clusters"), attrs.get("sources"))

    # ------------------------------------------------------------------ reporting
    def cluster_summary(self) -> list[dict]:
        rows = []
        for k in range(self.n_clusters):
            m = self.labels == k
            rows.append({
                "cluster": k, "name": self.cluster_names[k], "alpha": float(self.centres[k, 0]),
                "beta": float(self.centres[k, 1]), "count": int(m.sum()),
                "sid": float(self.table["sid"][m].mean()) if m.any() else float("nan"),
                "sod": float(self.table["sod"][m].mean()) if m.any() else float("nan"),
                "spacing": float(self.table["spacing_row"][m].mean()) if m.any() else float("nan"),
            })
        return rows

    def save_figure(self, path) -> Path:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 4, figsize=(18, 4), gridspec_kw={"width_ratios": [2.6, 1, 1, 1]})
        ax = axes[0]
        cmap = plt.get_cmap("tab10")
        for k in range(self.n_clusters):
            m = self.labels == k
            ax.scatter(self.table["alpha"][m], self.table["beta"][m], s=6, color=cmap(k % 10), alpha=0.6,
                       label=f"{k}: {self.cluster_names[k]}")
        if self.sampling == "clusters":
            ax.scatter(self.centres[:, 0], self.centres[:, 1], marker="x", color="black", s=60, label="centres")
        ax.set_xlabel("primary angle α (°, LAO +)")
        ax.set_ylabel("secondary angle β (°, CRA +)")
        ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        ax.grid(alpha=0.3)
        for ax, (key, label) in zip(axes[1:], [("sid", "SID (mm)"), ("sod", "SOD (mm)"), ("spacing_row", "detector spacing (mm)")]):
            ax.hist(self.table[key], bins=30, color="#4477aa")
            ax.set_xlabel(label)
        fig.suptitle(f"pose model: {len(self)} poses, {self.n_clusters} cluster(s)")
        fig.tight_layout()
        return save_png(fig, path, dpi=100)


def _view_name(alpha: float, beta: float) -> str:
    lr = "AP" if abs(alpha) < 10 else ("LAO" if alpha > 0 else "RAO")
    cc = "" if abs(beta) < 10 else (" cranial" if beta > 0 else " caudal")
    return f"{lr} {abs(alpha):.0f}/{'+' if beta >= 0 else '−'}{abs(beta):.0f}{cc}"


def collect_poses(folder) -> tuple[list[dict], list[str], list[tuple[str, str]]]:
    """Read the geometry of every run under ``folder``: (poses, source paths, skipped (path, reason))."""
    poses, sources, skipped = [], [], []
    files = iter_dicom_files(folder)
    if not files:
        raise UserError(f"{folder}: no files found")
    for path in files:
        try:
            g = read_xa(path, load_pixels=False).geometry
        except UserError as exc:
            skipped.append((str(path), str(exc).removeprefix(f"{path}: ")))
            continue
        poses.append({"alpha": g.alpha, "beta": g.beta, "sid": g.sid, "sod": g.sod, "spacing_row": g.spacing[0],
                      "spacing_col": g.spacing[1], "rows": g.rows, "cols": g.cols})
        sources.append(str(path))
    return poses, sources, skipped


def fit_poses(folder, n_clusters: int = 9, seed: int = 0):
    """Collect poses under ``folder`` and cluster them. Returns (model, skipped files)."""
    poses, sources, skipped = collect_poses(folder)
    for path, reason in skipped:
        log.warning("skipped %s: %s", path, reason)
    if not poses:
        raise UserError(f"{folder}: none of {len(skipped)} file(s) is a usable XA run")
    if len(poses) < n_clusters:
        raise UserError(f"{folder}: {len(poses)} usable run(s) ({len(skipped)} skipped) for {n_clusters} clusters; lower --clusters")
    return PoseModel.fit(poses, n_clusters, seed=seed, sources=sources), skipped

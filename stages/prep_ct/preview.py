"""PNG preview of a prepared case: three orthogonal maximum projections of the lumen labels (world
axes, LPS) with the centreline graph drawn over them, junctions and endpoints marked."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def save_preview(case, path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..core.figures import save_png

    lab = case.labels
    occ, lo = lab.to_dense("occupancy")
    origin = lab.origin + lo * lab.voxel_size
    v = lab.voxel_size
    # (projection axis, horizontal world axis, vertical world axis)
    views = [(2, 0, 1, "axial: x left →, y posterior ↓"), (1, 0, 2, "coronal: x left →, z superior ↑"),
             (0, 1, 2, "sagittal: y posterior →, z superior ↑")]
    deg = np.bincount(case.edges.ravel(), minlength=len(case.nodes)) if len(case.edges) else np.zeros(len(case.nodes))
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.4))
    for ax, (proj, h, vv, title) in zip(axes, views):
        mip = occ.max(axis=proj).astype(float)
        if h > vv:
            mip = mip.T
        # mip[i, j] with i along world axis h, j along vv → image rows = vv, cols = h
        ext = [origin[h] - v / 2, origin[h] + (occ.shape[h] - 0.5) * v,
               origin[vv] - v / 2, origin[vv] + (occ.shape[vv] - 0.5) * v]
        ax.imshow(mip.T, origin="lower", extent=ext, cmap="gray", vmin=0, vmax=1.6, interpolation="nearest")
        if vv == 1:  # posterior down in the axial view
            ax.invert_yaxis()
        for a, b in case.edges:
            ax.plot(case.nodes[[a, b], h], case.nodes[[a, b], vv], "-", color="tab:red", lw=0.8)
        j = deg >= 3
        e = deg == 1
        ax.plot(case.nodes[j, h], case.nodes[j, vv], "o", ms=3, color="tab:orange")
        ax.plot(case.nodes[e, h], case.nodes[e, vv], "o", ms=2, color="tab:cyan")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("mm")
        ax.set_aspect("equal")
    n_bif = int(np.maximum(deg - 2, 0).sum())
    fig.suptitle(f"{case.case_id} {case.side}: {len(case.faces)} faces, {len(case.nodes)} centreline nodes, "
                 f"{n_bif} bifurcations, {int(case.labels.features['occupancy'].sum())} lumen voxels "
                 f"at {lab.voxel_size:g} mm", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    return save_png(fig, path, dpi=80)

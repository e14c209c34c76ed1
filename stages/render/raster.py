"""Silhouettes and lumen path lengths of triangle meshes under a C-arm camera, in NumPy.

Reads nothing from disk. These functions serve the rest of :mod:`stages.render`:

* :func:`rasterise_mask` — the lumen silhouette: every pixel whose centre's ray meets the mesh. This is
  the fast path used for training pairs. It is an exact triangle raster of the prepared mesh (not an
  approximation by centreline capsules): each triangle is projected, its pixel bounding box enumerated
  in bulk (a ragged expansion, so triangles of any size work) and pixel centres tested with edge
  functions. For a closed mesh every ray that meets the mesh crosses a front-facing triangle, so only
  one orientation class of faces is drawn (half the work, same silhouette). Pixel centres sit at
  integer (row, col) indices (DESIGN.md §2), the same samples the ray-cast uses, which is why the
  raster agrees with :func:`raycast_mask` to the pixel.
* :func:`rasterise_path_length` — per pixel, the length (mm) of the ray inside the lumen, optionally
  weighted per face (e.g. iodine concentration): Σ over exiting faces of the ray depth minus Σ over
  entering faces (perspective-correct depth interpolation). This is the line integral the XA simulator
  turns into attenuation, so stenoses and foreshortened segments darken as in clinical images.
  :func:`rasterise_lumen` returns it together with the silhouette from the same raster pass (one pass
  per simulated XA frame instead of two).
* :func:`raycast_mask` — the *reference*: Möller–Trumbore ray/triangle intersection in 3D, vectorised
  over (ray, triangle) candidate pairs found through a coarse tile binning. Slow-ish; used by tests.

:func:`boundary_disagreement` measures how far (in pixels) the mismatched pixels of a silhouette lie
from the reference silhouette's boundary.
"""

from __future__ import annotations

import numpy as np

from ..core.geometry import Camera

__all__ = [
    "rasterise_mask",
    "rasterise_path_length",
    "rasterise_lumen",
    "raycast_mask",
    "boundary_disagreement",
    "project_vertices",
]


def project_vertices(vertices, camera: Camera, offset_rc=None):
    """(rc V×2, depth V) of world vertices; ``offset_rc`` (V×2 px) is added after projection (2D warps)."""
    rc, depth = camera.project(np.asarray(vertices, dtype=float), return_depth=True)
    if offset_rc is not None:
        rc = rc + offset_rc
    return rc, depth


def _front_faces(tri_rc: np.ndarray, camera: Camera) -> np.ndarray:
    """Indices of faces whose normal points toward the source (one orientation class of a closed mesh).

    Decided in the image: for vertices in front of the source, n·(a − S) = det[a−S, b−S, c−S] has the
    sign of det(K)·det(R) times the signed area of the projected triangle (the homogeneous coordinates
    are the camera-frame points times K, and their third components, the depths, are positive). That
    costs a few subtractions on the projected triangles ``tri_rc`` (F×3×2, row/col) instead of a 3D
    cross product per face.
    """
    r, c = tri_rc[..., 0], tri_rc[..., 1]
    area = (c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0]) - (c[:, 2] - c[:, 0]) * (r[:, 1] - r[:, 0])
    handed = np.sign(np.linalg.det(camera.K) * np.linalg.det(camera.R))
    return np.flatnonzero(handed * area < 0)


def _min3(x: np.ndarray) -> np.ndarray:
    # element-wise over the three vertices: much faster than x.min(axis=1) on an F×3 array
    return np.minimum(np.minimum(x[:, 0], x[:, 1]), x[:, 2])


def _max3(x: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(x[:, 0], x[:, 1]), x[:, 2])


def _enumerate(tri_rc: np.ndarray, rows: int, cols: int, chunk: int = 4_000_000):
    """Yield (face index, pixel row, pixel col, barycentrics n×3) for pixel centres inside each triangle.

    ``tri_rc`` is F×3×2 (row, col). A pixel centre exactly on an edge shared by two triangles is
    given to exactly one of them (a top-left style rule), so accumulations do not double count.
    """
    r = tri_rc[..., 0]
    c = tri_rc[..., 1]
    r0 = np.ceil(_min3(r)).clip(0, rows)
    r1 = np.floor(_max3(r)).clip(-1, rows - 1)
    c0 = np.ceil(_min3(c)).clip(0, cols)
    c1 = np.floor(_max3(c)).clip(-1, cols - 1)
    h = np.maximum(r1 - r0 + 1, 0)
    w = np.maximum(c1 - c0 + 1, 0)
    # a vertex behind the source (NaN) gives a NaN bounding box: such faces are dropped
    n = h * w
    n[np.isnan(n)] = 0
    n = n.astype(np.int64)
    w = np.where(n > 0, w, 0).astype(np.int64)
    keep = np.nonzero(n)[0]
    if keep.size == 0:
        return
    n = n[keep]
    # split the faces into chunks of about ``chunk`` candidate pixels each
    cum = np.cumsum(n)
    splits = np.searchsorted(cum, np.arange(chunk, cum[-1], chunk))
    splits = np.unique(np.concatenate([[0], splits, [len(keep)]]))
    for start, stop in zip(splits[:-1], splits[1:]):
        idx = keep[start:stop]
        nn = n[start:stop]
        fi = np.repeat(idx, nn)
        offs = np.arange(nn.sum()) - np.repeat(np.cumsum(nn) - nn, nn)
        ww = w[fi]
        pr = r0[fi].astype(np.int64) + offs // ww
        pc = c0[fi].astype(np.int64) + offs % ww
        t = tri_rc[fi]
        y, x = pr.astype(float), pc.astype(float)
        # edge functions in (x = col, y = row)
        e = np.empty((len(fi), 3))
        inc = np.empty((len(fi), 3), dtype=bool)
        for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # edge opposite vertex k
            ax, ay = t[:, i, 1], t[:, i, 0]
            dx, dy = t[:, j, 1] - ax, t[:, j, 0] - ay
            e[:, k] = dx * (y - ay) - dy * (x - ax)
            inc[:, k] = (dy > 0) | ((dy == 0) & (dx < 0))
        area = e.sum(axis=1)
        sgn = np.sign(area)
        es = e * sgn[:, None]
        # for negatively oriented triangles the edges run the other way: flip the tie rule
        inc = np.where(sgn[:, None] > 0, inc, ~inc)
        ok = (area != 0) & np.all((es > 0) | ((es == 0) & inc), axis=1)
        if not ok.any():
            continue
        bary = es[ok] / np.abs(area[ok])[:, None]
        yield fi[ok], pr[ok], pc[ok], bary


def _mask_pixels(tri_rc: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Flat indices of pixel centres covered by any triangle (inclusive edges), float32 edge functions.

    The silhouette is a union, so no tie rule or barycentrics are needed: this is the lean version of
    :func:`_enumerate` that the training-pair path uses.
    """
    t = tri_rc.astype(np.float32)
    r, c = t[..., 0], t[..., 1]
    r0 = np.ceil(_min3(r)).clip(0, rows)
    r1 = np.floor(_max3(r)).clip(-1, rows - 1)
    c0 = np.ceil(_min3(c)).clip(0, cols)
    c1 = np.floor(_max3(c)).clip(-1, cols - 1)
    h = np.maximum(r1 - r0 + 1, 0).astype(np.int32)
    w = np.maximum(c1 - c0 + 1, 0).astype(np.int32)
    n = h * w
    n[~np.all(np.isfinite(t.reshape(len(t), -1)), axis=1)] = 0
    keep = np.flatnonzero(n)
    if keep.size == 0:
        return np.zeros(0, np.int64)
    t, n, w, r0, c0 = t[keep], n[keep], w[keep], r0[keep].astype(np.int32), c0[keep].astype(np.int32)
    # edge function coefficients per face: e_k(x, y) = A_k x + B_k y + C_k  (x = col, y = row)
    A = np.empty((len(t), 3), np.float32)
    B = np.empty_like(A)
    C = np.empty_like(A)
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        ay, ax = t[:, i, 0], t[:, i, 1]
        dy, dx = t[:, j, 0] - ay, t[:, j, 1] - ax
        A[:, k], B[:, k], C[:, k] = -dy, dx, dy * ax - dx * ay
    fi = np.repeat(np.arange(len(t), dtype=np.int32), n)
    offs = np.arange(len(fi), dtype=np.int32) - np.repeat((np.cumsum(n) - n).astype(np.int32), n)
    ww = w[fi]
    pr = r0[fi] + offs // ww
    pc = c0[fi] + offs % ww
    x, y = pc.astype(np.float32), pr.astype(np.float32)
    pos = np.ones(len(fi), bool)
    neg = np.ones(len(fi), bool)
    nz = np.zeros(len(fi), bool)
    for k in range(3):
        e = A[fi, k] * x + B[fi, k] * y + C[fi, k]
        pos &= e >= 0
        neg &= e <= 0
        nz |= e != 0
    hit = (pos | neg) & nz
    return pr[hit].astype(np.int64) * cols + pc[hit]


def rasterise_mask(vertices, faces, camera: Camera, offset_rc=None, cull: bool = True) -> np.ndarray:
    """Boolean rows×cols silhouette of a closed mesh; ``offset_rc`` per-vertex 2D displacement (px)."""
    rows, cols = camera.rows, camera.cols
    rc, _ = project_vertices(vertices, camera, offset_rc)
    tri = rc[np.asarray(faces)]
    if cull:
        tri = tri[_front_faces(tri, camera)]
    mask = np.zeros(rows * cols, dtype=bool)
    mask[_mask_pixels(tri, rows, cols)] = True
    return mask.reshape(rows, cols)


def rasterise_path_length(vertices, faces, camera: Camera, face_weight=None, offset_rc=None) -> np.ndarray:
    """Float32 rows×cols: length (mm) of each pixel-centre ray inside the closed mesh.

    Σ over exiting faces of the ray depth − Σ over entering faces, exact for a closed mesh. With
    ``face_weight`` (F,) the length is multiplied by the mean weight of the faces the ray crosses
    (e.g. iodine concentration): weighting the depths themselves would amplify small front/back weight
    differences by the ~1 m source distance.
    """
    return rasterise_lumen(vertices, faces, camera, face_weight, offset_rc)[1]


def rasterise_lumen(vertices, faces, camera: Camera, face_weight=None, offset_rc=None) -> tuple[np.ndarray, np.ndarray]:
    """(silhouette, path length) of a closed mesh from one raster pass (see :func:`rasterise_path_length`).

    The silhouette is the set of pixel centres inside a front-facing triangle, taken from the same
    enumeration as the path length (the XA simulator needs both per frame). It equals
    :func:`rasterise_mask` except for a pixel centre lying exactly on a silhouette edge, which the
    enumeration's tie rule may give to the back face (inclusive float32 edges in ``rasterise_mask``).
    """
    rows, cols = camera.rows, camera.cols
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    rc, depth = project_vertices(v, camera, offset_rc)
    tri = rc[f]
    front = np.zeros(len(f), dtype=bool)
    front[_front_faces(tri, camera)] = True
    sign = np.where(front, -1.0, 1.0)
    # depths relative to a reference keep the float sums well conditioned
    z_ref = float(np.median(depth))
    inv_z = 1.0 / depth
    npx = rows * cols
    acc = np.zeros(npx)
    mask = np.zeros(npx, dtype=bool)
    weight = None if face_weight is None else np.asarray(face_weight, float)
    wsum = np.zeros(npx) if weight is not None else None
    count = np.zeros(npx) if weight is not None else None
    for fi, pr, pc, bary in _enumerate(tri, rows, cols):
        # perspective-correct: 1/z is affine in screen coordinates
        fv = f[fi]
        iz = bary[:, 0] * inv_z[fv[:, 0]] + bary[:, 1] * inv_z[fv[:, 1]] + bary[:, 2] * inv_z[fv[:, 2]]
        idx = pr * cols + pc
        acc += np.bincount(idx, weights=sign[fi] * (1.0 / iz - z_ref), minlength=npx)
        mask[idx[front[fi]]] = True
        if weight is not None:
            wsum += np.bincount(idx, weights=weight[fi], minlength=npx)
            count += np.bincount(idx, minlength=npx)
    z_len = acc.reshape(rows, cols)
    if weight is not None:
        z_len = z_len * (wsum / np.maximum(count, 1)).reshape(rows, cols)
    # depth along the principal axis → length along each pixel's ray
    Kinv = np.linalg.inv(camera.K)
    cc, rr = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    ray = np.stack([cc, rr, np.ones_like(cc)], axis=-1) @ Kinv.T
    scale = np.linalg.norm(ray, axis=-1) / ray[..., 2]
    return mask.reshape(rows, cols), np.maximum(z_len * scale, 0.0).astype(np.float32)


def raycast_mask(vertices, faces, camera: Camera, tile: int = 8, eps: float = 1e-12) -> np.ndarray:
    """Reference silhouette by exact 3D ray casting (Möller–Trumbore) through every pixel centre.

    Candidate (pixel, triangle) pairs come from binning each triangle's projected bounding box (plus a
    one-pixel margin) into ``tile``×``tile`` pixel tiles; the hit test itself is done in 3D on the ray
    through the pixel centre, independent of the 2D edge functions of :func:`rasterise_mask`.
    """
    rows, cols = camera.rows, camera.cols
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    rc = camera.project(v)
    tri = rc[f]
    tr0 = np.floor((np.nanmin(tri[..., 0], 1) - 1) / tile).clip(0, (rows - 1) // tile).astype(int)
    tr1 = np.floor((np.nanmax(tri[..., 0], 1) + 1) / tile).clip(0, (rows - 1) // tile).astype(int)
    tc0 = np.floor((np.nanmin(tri[..., 1], 1) - 1) / tile).clip(0, (cols - 1) // tile).astype(int)
    tc1 = np.floor((np.nanmax(tri[..., 1], 1) + 1) / tile).clip(0, (cols - 1) // tile).astype(int)
    inside = (np.nanmax(tri[..., 0], 1) >= -1) & (np.nanmin(tri[..., 0], 1) <= rows) & \
             (np.nanmax(tri[..., 1], 1) >= -1) & (np.nanmin(tri[..., 1], 1) <= cols)
    ntc = (cols - 1) // tile + 1
    tiles: dict[int, list] = {}
    for fi in np.nonzero(inside)[0]:
        for a in range(tr0[fi], tr1[fi] + 1):
            for b in range(tc0[fi], tc1[fi] + 1):
                tiles.setdefault(a * ntc + b, []).append(fi)
    mask = np.zeros((rows, cols), dtype=bool)
    A, B, C = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    E1, E2 = B - A, C - A
    for key, flist in tiles.items():
        a, b = divmod(key, ntc)
        rr, cc = np.mgrid[a * tile:min((a + 1) * tile, rows), b * tile:min((b + 1) * tile, cols)]
        pix = np.stack([rr.ravel(), cc.ravel()], axis=1).astype(float)
        o, d = camera.rays(pix)
        fl = np.asarray(flist)
        # all pairs (pixel, face)
        D = d[:, None, :]
        e1, e2 = E1[fl][None], E2[fl][None]
        p = np.cross(D, e2)
        det = np.einsum("ijk,ijk->ij", e1, p)
        good = np.abs(det) > eps
        inv = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
        s = o[:, None, :] - A[fl][None]
        u = np.einsum("ijk,ijk->ij", s, p) * inv
        q = np.cross(s, e1)
        w = np.einsum("ijk,ijk->ij", D, q) * inv
        t = np.einsum("ijk,ijk->ij", e2, q) * inv
        hit = good & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        mask[rr.ravel(), cc.ravel()] |= hit.any(axis=1)
    return mask


def boundary_disagreement(mask: np.ndarray, reference: np.ndarray) -> dict:
    """Distance (px) from each mismatched pixel centre to the reference silhouette's boundary.

    The reference boundary runs along pixel edges between inside and outside pixels, so a mismatch
    right next to it counts 0.5 px. Returns ``max_px``, ``p95_px``, ``n_mismatch``, ``n_boundary``.
    """
    from scipy import ndimage

    ref = np.asarray(reference, bool)
    m = np.asarray(mask, bool)
    bad = m != ref
    n_boundary = int((ref & ~ndimage.binary_erosion(ref)).sum())
    if not bad.any():
        return {"max_px": 0.0, "p95_px": 0.0, "n_mismatch": 0, "n_boundary": n_boundary}
    # distance of a pixel centre to the nearest pixel of the other class, minus half a pixel
    d_in = ndimage.distance_transform_edt(ref)  # inside pixels: distance to nearest outside pixel
    d_out = ndimage.distance_transform_edt(~ref)
    d = np.where(ref, d_in, d_out)[bad] - 0.5
    return {"max_px": float(d.max()), "p95_px": float(np.percentile(d, 95)), "n_mismatch": int(bad.sum()),
            "n_boundary": n_boundary}

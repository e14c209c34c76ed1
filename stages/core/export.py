"""Exports for other tools, written beside the artefacts (DESIGN.md §4). All writes are atomic.

* :func:`write_vtp` — a vascular graph as VTK XML PolyData (``.vtp``): one polyline per curve segment
  (paths between junctions/end points, so junction points are shared), point data ``Radius`` (mm), the
  same values as ``MaximumInscribedSphereRadius`` (the VMTK centreline name 3D Slicer's tools look for)
  and ``NodeId``; cell data ``CenterlineIds`` (one id per branch, VMTK's cell array name) and
  ``SegmentId`` (the same ids, kept for older readers); optional per-node text labels (the vessel names and
  segments QCA gives) as point and cell string arrays. Coordinates are world mm in DICOM LPS, the
  convention 3D Slicer assumes for model files, and the file says so: field data ``SPACE`` = ``LPS`` (the
  array Slicer's model reader looks for) and ``Units`` = ``mm``. Readable by VTK (``vtkXMLPolyDataReader``),
  ParaView, PyVista, Slicer.
* :func:`write_lumen_surface` — the lumen of a graph as a triangle mesh (``.stl`` or ``.ply``, via
  trimesh): marching cubes (scikit-image) of the implicit tube field max over edges of
  (interpolated radius − distance to the edge), on a grid of ``voxel_mm``; watertight, outward normals.
* :func:`write_graph_json` — the graph as JSON (nodes, radius, edges, node ids, units, frame + extras) and,
  given the views' cameras, its 2D↔2D correspondences (:func:`graph_correspondences`): every node's pixel
  in each view, so one node index names the same vessel point in both runs' key frames.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from .artefacts import atomic_path, write_json

__all__ = ["write_vtp", "lumen_mesh", "write_lumen_surface", "write_graph_json", "graph_correspondences"]


def _ascii(values, fmt) -> str:
    flat = np.asarray(values).ravel()
    return " ".join(fmt % v for v in flat) if len(flat) else ""


def _ascii_strings(values) -> str:
    """Strings as VTK XML writes them in ASCII: each character's code, each string ended by a 0."""
    return " ".join(" ".join([*(str(b) for b in str(v).encode("utf-8")), "0"]) for v in values)


def _string_array(name: str, values) -> str:
    return (f'        <DataArray type="String" Name="{name}" NumberOfTuples="{len(values)}" format="ascii">'
            f"{_ascii_strings(values)}</DataArray>")


def write_vtp(path, graph, node_labels: dict | None = None) -> Path:
    """VTK XML PolyData centreline with radius point data (see the module docstring).

    ``node_labels``: array name → one string per node (e.g. ``VesselName``), written as point data and as
    cell data, where each branch takes the label of its middle point (its ends are shared junctions)."""
    segs = graph.segments()
    conn = np.concatenate(segs) if segs else np.zeros(0, np.int64)
    offsets = np.cumsum([len(s) for s in segs]).astype(np.int64) if segs else np.zeros(0, np.int64)
    n = len(graph)
    radius = _ascii(graph.radius.astype(np.float32), "%.5g")
    branch_ids = _ascii(np.arange(len(segs)), "%d")
    point_labels, cell_labels = [], []
    for name, values in sorted((node_labels or {}).items()):
        if len(values) != n:
            raise ValueError(f"label {name!r}: {len(values)} values for {n} nodes")
        point_labels.append(_string_array(name, list(values)))
        cell_labels.append(_string_array(name, [values[int(s[len(s) // 2])] for s in segs]))
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        "  <PolyData>",
        "    <FieldData>",
        _string_array("SPACE", ["LPS"]),
        _string_array("Units", ["mm"]),
        "    </FieldData>",
        f'    <Piece NumberOfPoints="{n}" NumberOfVerts="0" NumberOfLines="{len(segs)}" NumberOfStrips="0" '
        'NumberOfPolys="0">',
        '      <PointData Scalars="Radius">',
        f'        <DataArray type="Float32" Name="Radius" format="ascii">{radius}</DataArray>',
        f'        <DataArray type="Float32" Name="MaximumInscribedSphereRadius" format="ascii">{radius}</DataArray>',
        f'        <DataArray type="Int64" Name="NodeId" format="ascii">{_ascii(graph.node_id, "%d")}</DataArray>',
        *point_labels,
        "      </PointData>",
        '      <CellData Scalars="CenterlineIds">',
        f'        <DataArray type="Int32" Name="CenterlineIds" format="ascii">{branch_ids}</DataArray>',
        f'        <DataArray type="Int32" Name="SegmentId" format="ascii">{branch_ids}</DataArray>',
        *cell_labels,
        "      </CellData>",
        "      <Points>",
        f'        <DataArray type="Float32" NumberOfComponents="3" format="ascii">'
        f'{_ascii(graph.nodes.astype(np.float32), "%.6g")}</DataArray>',
        "      </Points>",
        "      <Lines>",
        f'        <DataArray type="Int64" Name="connectivity" format="ascii">{_ascii(conn, "%d")}</DataArray>',
        f'        <DataArray type="Int64" Name="offsets" format="ascii">{_ascii(offsets, "%d")}</DataArray>',
        "      </Lines>",
        "    </Piece>",
        "  </PolyData>",
        "</VTKFile>",
        "",
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return Path(path)


# The tube field is a dense grid over the graph's bounding box: cap it (256 MB of float32) so a graph with
# far-apart pieces cannot ask for gigabytes (one did: 15 GiB, for nodes 900 mm apart).
MAX_FIELD_VOXELS = 64_000_000


def lumen_mesh(graph, voxel_mm: float = 0.4):
    """Watertight lumen surface of a graph as a ``trimesh.Trimesh`` (marching cubes of the tube field).

    Within :data:`MAX_FIELD_VOXELS`: one field over the whole graph. Beyond it, each connected piece is
    meshed in its own box (the pieces' meshes concatenated), and a piece still too large is meshed on a
    grid coarsened just enough to fit.
    """
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not len(graph.edges):
        raise ValueError("graph has no edges: no lumen surface to build")
    P, r, E = graph.nodes, graph.radius, np.asarray(graph.edges)
    if _field_voxels(P, r, voxel_mm) <= MAX_FIELD_VOXELS:
        return _tube_mesh(P, r, E, voxel_mm)
    n, label = connected_components(coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(len(P), len(P))),
                                    directed=False)
    meshes = []
    for c in range(n):
        nodes = np.flatnonzero(label == c)
        edges = E[label[E[:, 0]] == c]
        if not len(edges):
            continue  # an isolated node has no lumen
        remap = np.full(len(P), -1)
        remap[nodes] = np.arange(len(nodes))
        Pc, rc = P[nodes], r[nodes]
        voxels = _field_voxels(Pc, rc, voxel_mm)
        piece_voxel = voxel_mm * max(1.0, (voxels / MAX_FIELD_VOXELS) ** (1 / 3))
        meshes.append(_tube_mesh(Pc, rc, remap[edges], piece_voxel))
    return trimesh.util.concatenate(meshes)


def _field_voxels(P, r, voxel_mm: float) -> float:
    pad = float(r.max()) + 2 * voxel_mm
    return float(np.prod((P.max(0) - P.min(0) + 2 * pad) / voxel_mm + 1))


@njit(cache=True, nogil=True)
def _capsule_field(field, P, r, edges, origin, voxel_mm):
    """Raise ``field`` (in place) to each edge's tapered-capsule value, radius − distance to the segment, in the
    edge's box (its radius + 2 voxels around it). Compiled: a graph has hundreds of short edges, and the NumPy
    version spent its time in per-edge overhead."""
    shape = field.shape
    for e in range(len(edges)):
        a, b = edges[e, 0], edges[e, 1]
        reach = max(r[a], r[b]) + 2 * voxel_mm
        lo = np.empty(3, np.int64)
        hi = np.empty(3, np.int64)
        d = np.empty(3)
        for k in range(3):
            lo[k] = max(int(np.floor((min(P[a, k], P[b, k]) - reach - origin[k]) / voxel_mm)), 0)
            hi[k] = min(int(np.ceil((max(P[a, k], P[b, k]) + reach - origin[k]) / voxel_mm)) + 1, shape[k])
            d[k] = P[b, k] - P[a, k]
        dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        for i in range(lo[0], hi[0]):
            x0 = origin[0] + voxel_mm * i - P[a, 0]
            for j in range(lo[1], hi[1]):
                x1 = origin[1] + voxel_mm * j - P[a, 1]
                for k in range(lo[2], hi[2]):
                    x2 = origin[2] + voxel_mm * k - P[a, 2]
                    t = 0.0
                    if dd > 0:
                        t = min(max((x0 * d[0] + x1 * d[1] + x2 * d[2]) / dd, 0.0), 1.0)
                    e0, e1, e2 = x0 - t * d[0], x1 - t * d[1], x2 - t * d[2]
                    val = np.float32(r[a] + t * (r[b] - r[a]) - np.sqrt(e0 * e0 + e1 * e1 + e2 * e2))
                    if val > field[i, j, k]:
                        field[i, j, k] = val


# Marching cubes runs block by block over the tube field: the tubes fill a few per cent of their bounding box,
# and a block whose points all lie outside every tube has no surface to find.
MESH_BLOCK = 16


def _tube_mesh(P, r, edges, voxel_mm: float):
    import trimesh

    pad = float(r.max()) + 2 * voxel_mm
    origin = P.min(0) - pad
    shape = tuple((np.ceil((P.max(0) + pad - origin) / voxel_mm).astype(int) + 1).tolist())
    field = np.full(shape, -voxel_mm * 4, np.float32)  # negative outside; only a band near the tubes is set
    _capsule_field(field, np.asarray(P, np.float64), np.asarray(r, np.float64), np.asarray(edges, np.int64).reshape(-1, 2),
                   np.asarray(origin, np.float64), float(voxel_mm))
    # a level a hair above zero: grid points lying exactly on the surface make marching cubes emit
    # non-manifold (4- and 6-face) edges
    verts, faces = _blocked_marching_cubes(field, level=1e-3 * voxel_mm)
    # marching cubes' winding depends on the field's sign convention: make the normals outward (a negative
    # signed volume, Σ v0·(v1 × v2) / 6, means inward; trimesh's mass properties compute the same, slower)
    tri = verts[faces]
    if np.einsum("ij,ij->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) < 0:
        faces = faces[:, ::-1]
    return trimesh.Trimesh(verts * voxel_mm + origin, faces, process=True)


def _blocks_any(a, axis: int, block: int):
    """Along ``axis``: whether any of the points b·block … (b + 1)·block (both ends: the cells of block b touch
    them all) is set, for every block b of cells."""
    n_blocks = -(-(a.shape[axis] - 1) // block)
    pad = [(0, 0)] * 3
    pad[axis] = (0, n_blocks * block + 1 - a.shape[axis])
    a = np.moveaxis(np.pad(a, pad), axis, 0)
    inner = a[:n_blocks * block].reshape(n_blocks, block, *a.shape[1:]).any(1)
    return np.moveaxis(inner | a[block::block], 0, axis)


def _blocked_marching_cubes(field, level: float, block: int = MESH_BLOCK):
    """Marching cubes of ``field`` (vertices in grid index units, float64) run only on the blocks of ``block``³
    cells that hold a grid point above ``level``; the same triangles as one run over the whole field. Each cell
    belongs to one block, and a vertex on a face two blocks share comes out bit-identical from both (the same
    two field values, the same local index along the face, an exact integer across it), so merging duplicate
    vertices stitches the blocks together."""
    from skimage.measure import marching_cubes

    occupied = field > level
    for axis in range(3):
        occupied = _blocks_any(occupied, axis, block)
    verts, faces, count = [], [], 0
    for b in np.argwhere(occupied):
        start = b * block
        sub = field[start[0]:start[0] + block + 1, start[1]:start[1] + block + 1, start[2]:start[2] + block + 1]
        v, f, _, _ = marching_cubes(sub, level=level)
        verts.append(v.astype(np.float64) + start)
        faces.append(f + count)
        count += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(verts), np.concatenate(faces)


def write_lumen_surface(path, graph, voxel_mm: float = 0.4) -> Path:
    """Lumen surface as STL or PLY (by the file suffix)."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in ("stl", "ply"):
        raise ValueError(f"{path}: lumen surface must be .stl or .ply")
    mesh = lumen_mesh(graph, voxel_mm)
    with atomic_path(path) as tmp:
        mesh.export(str(tmp), file_type=fmt)
    return path


def graph_correspondences(graph, cameras: dict, source_frames: dict | None = None) -> dict:
    """The 2D↔2D correspondences a 3D model gives: each node projected into every view.

    ``cameras``: view name → :class:`stages.core.geometry.Camera`; ``source_frames``: view name → the index
    of the run's frame the view's key frame is. Returns ``{"pixel": ..., "views": {view: {source_frame,
    rows, cols, pixels}}, "pairs": ...}``: ``pixels`` holds one (row, col) per node, null where the node
    projects outside that image; with exactly two views, ``pairs`` lists [node, row_a, col_a, row_b,
    col_b] for the nodes inside both.
    """
    views, inside = {}, {}
    for name, cam in sorted(cameras.items()):
        rc = np.asarray(cam.project(graph.nodes), float).reshape(-1, 2)
        ok = np.all(np.isfinite(rc), 1) & np.all(rc >= -0.5, 1)
        ok &= (rc[:, 0] <= cam.rows - 0.5) & (rc[:, 1] <= cam.cols - 0.5)
        inside[name] = (rc, ok)
        # rounded once for the whole view: rounding node by node was a fifth of a second per key frame
        rounded = np.round(rc, 2).tolist()
        views[name] = {"source_frame": None if source_frames is None or name not in source_frames
                       else int(source_frames[name]), "rows": int(cam.rows), "cols": int(cam.cols),
                       "pixels": [p if k else None for p, k in zip(rounded, ok)]}
    out = {"pixel": "(row, col), 0-based, pixel centres at integer indices", "views": views}
    if len(inside) == 2:
        (rc_a, ok_a), (rc_b, ok_b) = inside.values()
        both = np.flatnonzero(ok_a & ok_b)
        out["pairs"] = np.round(np.column_stack([both, rc_a[both], rc_b[both]]), 2).tolist()
        for row in out["pairs"]:
            row[0] = int(row[0])
    return out


def write_graph_json(path, graph, cameras: dict | None = None, source_frames: dict | None = None, **extra) -> Path:
    """The graph as JSON: {units, frame, nodes, radius, edges, node_id, **extra}, plus ``correspondences``
    (:func:`graph_correspondences`) when the views' ``cameras`` are given."""
    doc = {**graph.to_dict(), **extra}
    if cameras:
        doc["correspondences"] = graph_correspondences(graph, cameras, source_frames)
    return write_json(path, doc)

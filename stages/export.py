"""Exports for other tools, written beside the artefacts (DESIGN.md §4). All writes are atomic.

* :func:`write_vtp` — a vascular graph as VTK XML PolyData (``.vtp``): one polyline per curve segment
  (paths between junctions/end points, so junction points are shared), point data ``Radius`` (mm), the
  same values as ``MaximumInscribedSphereRadius`` (the VMTK centreline name 3D Slicer's tools look for)
  and ``NodeId``; cell data ``SegmentId``. Coordinates are world mm in DICOM LPS, the convention 3D
  Slicer assumes for model files. Readable by VTK (``vtkXMLPolyDataReader``), ParaView, PyVista, Slicer.
* :func:`write_lumen_surface` — the lumen of a graph as a triangle mesh (``.stl`` or ``.ply``, via
  trimesh): marching cubes (scikit-image) of the implicit tube field max over edges of
  (interpolated radius − distance to the edge), on a grid of ``voxel_mm``; watertight, outward normals.
* :func:`write_graph_json` — the graph as JSON (nodes, radius, edges, node ids, units, frame + extras).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .artefacts import atomic_path, write_json

__all__ = ["write_vtp", "lumen_mesh", "write_lumen_surface", "write_graph_json"]


def _ascii(values, fmt) -> str:
    flat = np.asarray(values).ravel()
    return " ".join(fmt % v for v in flat) if len(flat) else ""


def write_vtp(path, graph) -> Path:
    """VTK XML PolyData centreline with radius point data (see the module docstring)."""
    segs = graph.segments()
    conn = np.concatenate(segs) if segs else np.zeros(0, np.int64)
    offsets = np.cumsum([len(s) for s in segs]).astype(np.int64) if segs else np.zeros(0, np.int64)
    n = len(graph)
    radius = _ascii(graph.radius.astype(np.float32), "%.5g")
    lines = [
        '<?xml version="1.0"?>',
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        "  <PolyData>",
        f'    <Piece NumberOfPoints="{n}" NumberOfVerts="0" NumberOfLines="{len(segs)}" NumberOfStrips="0" '
        'NumberOfPolys="0">',
        '      <PointData Scalars="Radius">',
        f'        <DataArray type="Float32" Name="Radius" format="ascii">{radius}</DataArray>',
        f'        <DataArray type="Float32" Name="MaximumInscribedSphereRadius" format="ascii">{radius}</DataArray>',
        f'        <DataArray type="Int64" Name="NodeId" format="ascii">{_ascii(graph.node_id, "%d")}</DataArray>',
        "      </PointData>",
        '      <CellData Scalars="SegmentId">',
        f'        <DataArray type="Int32" Name="SegmentId" format="ascii">{_ascii(np.arange(len(segs)), "%d")}</DataArray>',
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


def lumen_mesh(graph, voxel_mm: float = 0.4):
    """Watertight lumen surface of a graph as a ``trimesh.Trimesh`` (marching cubes of the tube field)."""
    import trimesh
    from skimage.measure import marching_cubes

    if not len(graph.edges):
        raise ValueError("graph has no edges: no lumen surface to build")
    P, r = graph.nodes, graph.radius
    pad = float(r.max()) + 2 * voxel_mm
    origin = P.min(0) - pad
    shape = tuple((np.ceil((P.max(0) + pad - origin) / voxel_mm).astype(int) + 1).tolist())
    field = np.full(shape, -voxel_mm * 4, np.float32)  # negative outside; only a band near the tubes is set
    for a, b in graph.edges:
        pa, pb = P[a], P[b]
        reach = max(r[a], r[b]) + 2 * voxel_mm
        i0 = np.maximum(np.floor((np.minimum(pa, pb) - reach - origin) / voxel_mm).astype(int), 0)
        i1 = np.minimum(np.ceil((np.maximum(pa, pb) + reach - origin) / voxel_mm).astype(int) + 1, shape)
        axes = [origin[k] + voxel_mm * np.arange(i0[k], i1[k]) for k in range(3)]
        X = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
        d = pb - pa
        dd = float(d @ d)
        t = np.clip(((X - pa) @ d) / dd, 0, 1) if dd > 0 else np.zeros(X.shape[:3])
        dist = np.linalg.norm(X - (pa + t[..., None] * d), axis=-1)
        val = (r[a] + t * (r[b] - r[a]) - dist).astype(np.float32)
        view = field[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
        np.maximum(view, val, out=view)
    # a level a hair above zero: grid points lying exactly on the surface make marching cubes emit
    # non-manifold (4- and 6-face) edges
    verts, faces, _, _ = marching_cubes(field, level=1e-3 * voxel_mm, spacing=(voxel_mm,) * 3)
    mesh = trimesh.Trimesh(verts + origin, faces, process=True)
    if mesh.volume < 0:  # marching cubes' winding depends on the field's sign convention: make normals outward
        mesh.invert()
    return mesh


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


def write_graph_json(path, graph, **extra) -> Path:
    """The graph as JSON: {units, frame, nodes, radius, edges, node_id, **extra}."""
    return write_json(path, {**graph.to_dict(), **extra})

"""The prepared case: one coronary tree (left or right) ready for rendering, training and evaluation.

Written by ``autocar prep-ct`` (:mod:`stages.prep_ct`), read by ``render``, ``train`` and ``evaluate``
through :class:`PreparedCase` only. One zarr v3 group per case (``case_0007_left.zarr``), kind
``"autocar.prepared-case"``, schema version 1::

    attrs: standard header + case_id (str), side ("left" | "right"), source (dict),
           heart (optional {"centre": [x,y,z], "long_axis": [ux,uy,uz]}, mm, LPS, base→apex unit vector),
           stenoses (optional list of dicts)
    mesh/vertices        V×3 float32  world mm (LPS)
    mesh/faces           F×3 int32    watertight, outward normals (counter-clockwise seen from outside)
    centreline/nodes     N×3 float32  world mm
    centreline/radius    N   float32  mm
    centreline/edges     E×2 int32    node indices
    labels/              SparseVoxels group (0.5 mm default): features occupancy (uint8 0/1, paper Eq. 4)
                         and centreness (float32, paper Eq. 3), lumen plus a band of outside voxels
    truth/               synthetic cases only, the analytic ground truth:
      points P×3 float32, radius P float32, branch P int32 (points of a branch contiguous,
      proximal→distal), parent B int32 (−1 for a root); attrs {"names": [...]} (B branch names)

World frame: DICOM LPS in mm, origin at the C-arm isocentre (DESIGN.md §2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .errors import UserError
from .voxels import SparseVoxels

KIND = "autocar.prepared-case"
SCHEMA_VERSION = 1


@dataclass
class CaseTruth:
    """Analytic centreline of a synthetic tree: polylines with radius, one branch after another."""

    points: np.ndarray  # P×3 float32, mm
    radius: np.ndarray  # P float32, mm
    branch: np.ndarray  # P int32 branch id, contiguous and ordered proximal→distal
    parent: np.ndarray  # B int32 parent branch id, −1 for the root
    names: list[str] = field(default_factory=list)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float32).reshape(-1, 3)
        self.radius = np.asarray(self.radius, dtype=np.float32).reshape(-1)
        self.branch = np.asarray(self.branch, dtype=np.int32).reshape(-1)
        self.parent = np.asarray(self.parent, dtype=np.int32).reshape(-1)
        self.names = [str(n) for n in self.names] or [f"branch{i}" for i in range(len(self.parent))]
        if not (len(self.points) == len(self.radius) == len(self.branch)):
            raise ValueError("truth points, radius and branch must have the same length")
        if len(self.names) != len(self.parent):
            raise ValueError("truth needs one name per branch")

    def polylines(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(points K×3, radius K)] per branch id 0..B-1."""
        out = []
        for b in range(len(self.parent)):
            sel = self.branch == b
            out.append((self.points[sel].astype(float), self.radius[sel].astype(float)))
        return out


@dataclass
class PreparedCase:
    """One prepared coronary tree. Arrays are in world mm (LPS)."""

    case_id: str
    side: str  # "left" | "right"
    vertices: np.ndarray  # V×3 float32
    faces: np.ndarray  # F×3 int32
    nodes: np.ndarray  # N×3 float32
    radius: np.ndarray  # N float32
    edges: np.ndarray  # E×2 int32
    labels: SparseVoxels  # features occupancy (uint8), centreness (float32)
    source: dict = field(default_factory=dict)
    heart: Optional[dict] = None
    stenoses: Optional[list] = None
    truth: Optional[CaseTruth] = None
    path: Optional[Path] = None  # where it was loaded from (None for a fresh case)

    def __post_init__(self):
        if self.side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {self.side!r}")
        self.vertices = np.asarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int32).reshape(-1, 3)
        self.nodes = np.asarray(self.nodes, dtype=np.float32).reshape(-1, 3)
        self.radius = np.asarray(self.radius, dtype=np.float32).reshape(-1)
        self.edges = np.asarray(self.edges, dtype=np.int32).reshape(-1, 2)
        if len(self.radius) != len(self.nodes):
            raise ValueError("centreline radius must have one value per node")

    # ------------------------------------------------------------------ conveniences
    def graph(self):
        """The centreline as a networkx.Graph: node attrs ``pos`` (3,) and ``radius``; edge attr ``length``."""
        import networkx as nx

        g = nx.Graph()
        for i, (p, r) in enumerate(zip(self.nodes, self.radius)):
            g.add_node(i, pos=p.astype(float), radius=float(r))
        for a, b in self.edges:
            g.add_edge(int(a), int(b), length=float(np.linalg.norm(self.nodes[a] - self.nodes[b])))
        return g

    def mesh(self):
        """The lumen as a trimesh.Trimesh (no processing, so vertices stay as stored)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @property
    def heart_centre(self) -> Optional[np.ndarray]:
        return None if not self.heart else np.asarray(self.heart["centre"], dtype=float)

    @property
    def heart_long_axis(self) -> Optional[np.ndarray]:
        return None if not self.heart else np.asarray(self.heart["long_axis"], dtype=float)

    # ------------------------------------------------------------------ storage
    def save(self, path, *, stage: str = "prep-ct", inputs=(), parameters=None) -> Path:
        """Write the case atomically as a zarr artefact at ``path``; returns the path."""
        from .artefacts import write_zarr

        path = Path(path)
        extra: dict[str, Any] = {"case_id": str(self.case_id), "side": self.side, "source": dict(self.source)}
        if self.heart is not None:
            extra["heart"] = dict(self.heart)  # centre, long_axis (+ any extra description of the heart)
            extra["heart"]["centre"] = [float(v) for v in self.heart["centre"]]
            extra["heart"]["long_axis"] = [float(v) for v in self.heart["long_axis"]]
        if self.stenoses is not None:
            extra["stenoses"] = list(self.stenoses)
        with write_zarr(path, kind=KIND, schema_version=SCHEMA_VERSION, stage=stage, inputs=inputs,
                        parameters=parameters, extra_attrs=extra) as group:
            mesh = group.require_group("mesh")
            mesh.create_array("vertices", data=self.vertices)
            mesh.create_array("faces", data=self.faces)
            cl = group.require_group("centreline")
            cl.create_array("nodes", data=self.nodes)
            cl.create_array("radius", data=self.radius)
            cl.create_array("edges", data=self.edges)
            self.labels.write_to_group(group.require_group("labels"))
            if self.truth is not None:
                tg = group.require_group("truth")
                tg.create_array("points", data=self.truth.points)
                tg.create_array("radius", data=self.truth.radius)
                tg.create_array("branch", data=self.truth.branch)
                tg.create_array("parent", data=self.truth.parent)
                tg.attrs.update({"names": list(self.truth.names)})
        return path

    @classmethod
    def load(cls, path) -> "PreparedCase":
        """Read a prepared case; a wrong kind/version or a missing part is a UserError naming the file."""
        from .artefacts import read_zarr

        path = Path(path)
        group = read_zarr(path, kind=KIND, schema_version=SCHEMA_VERSION)
        attrs = dict(group.attrs)
        try:
            truth = None
            if "truth" in group:
                tg = group["truth"]
                truth = CaseTruth(tg["points"][...], tg["radius"][...], tg["branch"][...], tg["parent"][...],
                                  list(dict(tg.attrs).get("names", [])))
            return cls(
                case_id=str(attrs.get("case_id", path.stem)),
                side=attrs["side"],
                vertices=group["mesh/vertices"][...],
                faces=group["mesh/faces"][...],
                nodes=group["centreline/nodes"][...],
                radius=group["centreline/radius"][...],
                edges=group["centreline/edges"][...],
                labels=SparseVoxels.read_from_group(group["labels"]),
                source=dict(attrs.get("source", {})),
                heart=attrs.get("heart"),
                stenoses=attrs.get("stenoses"),
                truth=truth,
                path=path,
            )
        except (KeyError, ValueError) as exc:
            raise UserError(f"{path}: incomplete prepared case ({type(exc).__name__}: {exc})") from None

    def summary(self) -> dict:
        """Small numbers for CLI tables and logs."""
        return {
            "case_id": self.case_id, "side": self.side, "vertices": len(self.vertices), "faces": len(self.faces),
            "nodes": len(self.nodes), "edges": len(self.edges), "labels": len(self.labels),
            "inside": int(np.count_nonzero(self.labels.features.get("occupancy", []))),
        }


def find_cases(folder) -> list[Path]:
    """All prepared-case artefacts (``*.zarr`` with the right kind) directly inside ``folder``, sorted."""
    import json

    folder = Path(folder)
    if folder.suffix == ".zarr":
        return [folder]
    out = []
    for p in sorted(folder.glob("*.zarr")):
        meta = p / "zarr.json"
        try:
            if json.loads(meta.read_text()).get("attributes", {}).get("kind") == KIND:
                out.append(p)
        except (OSError, ValueError):
            continue
    return out

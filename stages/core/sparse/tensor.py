"""Sparse tensor type, coordinate hashing and cached kernel maps.

Coordinates are ``N×4`` int64 rows ``(batch, x, y, z)`` in units of the finest voxel (stride 1).
A tensor of stride ``s`` only has coordinates that are multiples of ``s``; its voxel with
coordinate ``c`` covers fine voxels ``c .. c+s-1`` per axis, so its centre lies at world position
``origin + (c + (s-1)/2) * voxel_size`` (mm). At stride 1 this is the :class:`stages.core.voxels.SparseVoxels`
convention ``origin + ijk * voxel_size``.

The hash is a sorted array of 64-bit keys (batch and the three axes packed into one int64) searched
with :func:`torch.searchsorted`, which runs unchanged on CPU and CUDA. Every kernel map (neighbour
table of a submanifold convolution, parent/child tables of a strided convolution) is cached on the
:class:`CoordinateSet` it was built for, so all layers working on the same coordinates share it.

``a + b`` of tensors on different coordinate sets is :func:`union` (here; :mod:`.ops` re-exports it).
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

# Key layout: 12 bits batch | 17 bits x | 17 bits y | 17 bits z (63 bits, always positive).
_AXIS_BITS = 17
_AXIS_OFFSET = 1 << (_AXIS_BITS - 1)
_AXIS_MASK = (1 << _AXIS_BITS) - 1
_BATCH_BITS = 12
# Coordinates must stay this far inside the packable range so neighbour queries (up to ±2 voxels at
# stride up to 2^8) never wrap into another key.
_MARGIN = 1 << 10
COORD_LIMIT = _AXIS_OFFSET - _MARGIN


def pack_keys(coords: torch.Tensor) -> torch.Tensor:
    """N×4 int64 ``(b, x, y, z)`` → N int64 keys whose order is (b, x, y, z) lexicographic."""
    c = coords.long()
    key = c[:, 0] << (3 * _AXIS_BITS)
    key = key | ((c[:, 1] + _AXIS_OFFSET) << (2 * _AXIS_BITS))
    key = key | ((c[:, 2] + _AXIS_OFFSET) << _AXIS_BITS)
    return key | (c[:, 3] + _AXIS_OFFSET)


def unpack_keys(keys: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`pack_keys`."""
    out = torch.empty(keys.shape[0], 4, dtype=torch.long, device=keys.device)
    out[:, 0] = keys >> (3 * _AXIS_BITS)
    out[:, 1] = ((keys >> (2 * _AXIS_BITS)) & _AXIS_MASK) - _AXIS_OFFSET
    out[:, 2] = ((keys >> _AXIS_BITS) & _AXIS_MASK) - _AXIS_OFFSET
    out[:, 3] = (keys & _AXIS_MASK) - _AXIS_OFFSET
    return out


def kernel_offsets(kernel_size: int, device=None, centred: bool = True) -> torch.Tensor:
    """K×3 offsets in (x, y, z) lexicographic order (``itertools.product``), i.e. the order of a
    flattened dense ``conv3d`` kernel. Centred kernels run over ``-r..r``, others over ``0..k-1``."""
    r = kernel_size // 2 if centred else 0
    rng = range(-r, kernel_size - r)
    return torch.tensor(list(itertools.product(rng, rng, rng)), dtype=torch.long, device=device)


class CoordinateSet:
    """An immutable set of voxel coordinates at one stride, with its hash and kernel-map cache.

    Row order is the caller's (features stay aligned with it). Coarse sets made by
    :meth:`downsample` are in key order, which keeps neighbours close in memory.
    """

    def __init__(self, coords: torch.Tensor, stride: int = 1, *, _sorted_keys=None, _check: bool = True):
        coords = torch.as_tensor(coords)
        if coords.ndim != 2 or coords.shape[1] != 4:
            raise ValueError(f"coordinates must be N×4 (batch, x, y, z), got shape {tuple(coords.shape)}")
        if coords.dtype.is_floating_point:
            raise ValueError("coordinates must be integers")
        self.coords = coords.long().contiguous()
        self.stride = int(stride)
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        if _check and len(self.coords):
            if int(self.coords[:, 1:].abs().max()) >= COORD_LIMIT:
                raise ValueError(f"coordinates must lie within ±{COORD_LIMIT}")
            b = self.coords[:, 0]
            if int(b.min()) < 0 or int(b.max()) >= (1 << _BATCH_BITS):
                raise ValueError(f"batch index must be in [0, {1 << _BATCH_BITS})")
            if self.stride > 1 and bool((self.coords[:, 1:] % self.stride != 0).any()):
                raise ValueError(f"coordinates of a stride-{self.stride} set must be multiples of {self.stride}")
        if _sorted_keys is not None:
            self.sorted_keys = _sorted_keys
            self.order = None  # identity: rows are already in key order
        else:
            self.sorted_keys, self.order = torch.sort(pack_keys(self.coords))
            if _check and len(self.coords) > 1 and bool((self.sorted_keys[1:] == self.sorted_keys[:-1]).any()):
                raise ValueError("duplicate coordinates in a sparse tensor")
        self.parent: CoordinateSet | None = None  # finer set this one was downsampled from
        self._cache: dict = {}

    def __len__(self) -> int:
        return self.coords.shape[0]

    @property
    def device(self):
        return self.coords.device

    def to(self, device) -> "CoordinateSet":
        """Same coordinates on another device (the cache is rebuilt there on demand)."""
        if torch.device(device) == self.device:
            return self
        return CoordinateSet(self.coords.to(device), self.stride, _check=False)

    # ------------------------------------------------------------------ hash lookup
    def lookup_keys(self, keys: torch.Tensor) -> torch.Tensor:
        """Row index of each key, −1 where absent."""
        n = len(self)
        if n == 0:
            return torch.full_like(keys, -1)
        pos = torch.searchsorted(self.sorted_keys, keys).clamp_(max=n - 1)
        found = self.sorted_keys[pos] == keys
        idx = pos if self.order is None else self.order[pos]
        return torch.where(found, idx, torch.full_like(idx, -1))

    def lookup(self, coords: torch.Tensor) -> torch.Tensor:
        """Row index of each ``(b, x, y, z)`` row, −1 where absent. Out-of-range rows are absent."""
        coords = coords.long()
        inside = (coords[:, 1:].abs() < COORD_LIMIT).all(1) & (coords[:, 0] >= 0) & (coords[:, 0] < (1 << _BATCH_BITS))
        idx = self.lookup_keys(pack_keys(torch.where(inside[:, None], coords, torch.zeros_like(coords))))
        return torch.where(inside, idx, torch.full_like(idx, -1))

    # ------------------------------------------------------------------ kernel maps
    def neighbour_map(self, kernel_size: int) -> torch.Tensor:
        """N×K int32 table: row of the neighbour at each kernel offset (times the stride), or N (the index
        of an appended zero row) where absent. Cached."""
        key = ("subm", kernel_size)
        if key not in self._cache:
            if kernel_size % 2 != 1:
                raise ValueError(f"submanifold kernels must be odd, got {kernel_size}")
            offsets = kernel_offsets(kernel_size, self.device) * self.stride
            n, k = len(self), offsets.shape[0]
            # Pack once, then shift keys by packed offsets: the margin guarantees no carry across fields.
            base = pack_keys(self.coords)
            off_keys = (offsets[:, 0] << (2 * _AXIS_BITS)) + (offsets[:, 1] << _AXIS_BITS) + offsets[:, 2]
            # int32 halves the table (index_select takes int32 indices on CPU and CUDA)
            table = torch.empty(n, k, dtype=torch.int32, device=self.device)
            chunk = max(1, (1 << 22) // max(k, 1))
            for s in range(0, n, chunk):
                q = base[s : s + chunk, None] + off_keys[None, :]
                idx = self.lookup_keys(q.reshape(-1)).view(-1, k)
                table[s : s + chunk] = torch.where(idx < 0, torch.full_like(idx, n), idx)
            self._cache[key] = table
        return self._cache[key]

    def downsample(self, factor: int = 2) -> "CoordinateSet":
        """Coarse set (stride × factor) covering this one; maps are cached on both sides."""
        key = ("down", factor)
        if key not in self._cache:
            cs = self.stride * factor
            coarse = self.coords.clone()
            coarse[:, 1:] = torch.div(coarse[:, 1:], cs, rounding_mode="floor") * cs
            ukeys, parent = torch.unique(pack_keys(coarse), sorted=True, return_inverse=True)
            out = CoordinateSet(unpack_keys(ukeys), cs, _sorted_keys=ukeys, _check=False)
            out.parent = self
            self._cache[key] = out
            self._cache[("transfer", id(out))] = (out, self._build_transfer(out, parent))
        return self._cache[key]

    def transfer_maps(self, coarse: "CoordinateSet"):
        """Maps between this (fine) set and a coarser set whose stride is a multiple of ours.

        Returns ``(flat_parent, child)``: ``flat_parent[i] = parent_row * F³ + octant`` for every fine
        row (``M * F³`` where the parent is absent) and ``child`` M×F³ giving the fine row in each
        octant of every coarse voxel (N where absent). ``F`` = coarse stride / fine stride. Cached.
        """
        key = ("transfer", id(coarse))
        hit = self._cache.get(key)
        if hit is None or hit[0] is not coarse:
            if coarse.stride % self.stride or coarse.stride <= self.stride:
                raise ValueError(f"cannot map stride {self.stride} onto stride {coarse.stride}")
            cs = coarse.stride
            pc = self.coords.clone()
            pc[:, 1:] = torch.div(pc[:, 1:], cs, rounding_mode="floor") * cs
            parent = coarse.lookup(pc)
            hit = (coarse, self._build_transfer(coarse, parent))
            self._cache[key] = hit
        return hit[1]

    def _build_transfer(self, coarse: "CoordinateSet", parent: torch.Tensor):
        f = coarse.stride // self.stride
        k = f**3
        rel = torch.div(self.coords[:, 1:] - torch.div(self.coords[:, 1:], coarse.stride, rounding_mode="floor") * coarse.stride,
                        self.stride, rounding_mode="floor")
        octant = (rel[:, 0] * f + rel[:, 1]) * f + rel[:, 2]
        m, n = len(coarse), len(self)
        valid = parent >= 0
        flat_parent = torch.where(valid, parent * k + octant, torch.full_like(parent, m * k))
        child = torch.full((m * k + 1,), n, dtype=torch.int32, device=self.device)
        child[flat_parent] = torch.arange(n, dtype=torch.int32, device=self.device)
        return flat_parent.int(), child[:-1].view(m, k)


def _as_origin(origin) -> tuple[float, float, float]:
    o = np.asarray(origin, dtype=float).reshape(3)
    return (float(o[0]), float(o[1]), float(o[2]))


class SparseTensor:
    """Features on a sparse set of voxels.

    ``SparseTensor(coords, feats, stride=1, voxel_size=1.0, origin=(0, 0, 0))``: ``coords`` is N×4
    ``(batch, x, y, z)`` or N×3 (batch 0) integer voxel indices in stride-1 units, ``feats`` N×C.
    Pass ``coordinate_set=`` instead of ``coords`` to share hash and kernel maps with another tensor.
    """

    __slots__ = ("cset", "feats", "voxel_size", "origin")

    def __init__(self, coords=None, feats=None, stride: int = 1, voxel_size: float = 1.0, origin=(0.0, 0.0, 0.0),
                 *, coordinate_set: CoordinateSet | None = None):
        if coordinate_set is None:
            coords = torch.as_tensor(coords)
            if coords.ndim == 2 and coords.shape[1] == 3:
                coords = torch.cat([torch.zeros_like(coords[:, :1]), coords], 1)
            device = feats.device if isinstance(feats, torch.Tensor) else coords.device
            coordinate_set = CoordinateSet(coords.to(device), stride)
        feats = torch.as_tensor(feats)
        if feats.ndim == 1:
            feats = feats[:, None]
        if feats.shape[0] != len(coordinate_set):
            raise ValueError(f"{feats.shape[0]} feature rows for {len(coordinate_set)} coordinates")
        if feats.device != coordinate_set.device:
            raise ValueError("features and coordinates must be on the same device")
        self.cset = coordinate_set
        self.feats = feats
        self.voxel_size = float(voxel_size)
        self.origin = _as_origin(origin)

    # ------------------------------------------------------------------ basics
    @property
    def coords(self) -> torch.Tensor:
        return self.cset.coords

    @property
    def stride(self) -> int:
        return self.cset.stride

    @property
    def device(self):
        return self.feats.device

    @property
    def num_channels(self) -> int:
        return self.feats.shape[1]

    def __len__(self) -> int:
        return self.feats.shape[0]

    def __repr__(self) -> str:
        return (f"SparseTensor(n={len(self)}, channels={self.num_channels}, stride={self.stride}, "
                f"voxel_size={self.voxel_size}, device={self.device})")

    def replace(self, feats: torch.Tensor) -> "SparseTensor":
        """Same coordinates (shared maps), new features."""
        return SparseTensor(feats=feats, voxel_size=self.voxel_size, origin=self.origin, coordinate_set=self.cset)

    def to(self, device=None, dtype=None) -> "SparseTensor":
        cset = self.cset if device is None else self.cset.to(device)
        return SparseTensor(feats=self.feats.to(device=device, dtype=dtype), voxel_size=self.voxel_size,
                            origin=self.origin, coordinate_set=cset)

    def __add__(self, other: "SparseTensor") -> "SparseTensor":
        if isinstance(other, SparseTensor):
            if other.cset is self.cset:
                return self.replace(self.feats + other.feats)
            return union(self, other)
        return self.replace(self.feats + other)

    def world_points(self) -> torch.Tensor:
        """N×3 voxel centres in world mm (float64 on the tensor's device)."""
        c = self.coords[:, 1:].double() + (self.stride - 1) / 2.0
        return torch.tensor(self.origin, dtype=torch.float64, device=self.device) + c * self.voxel_size

    def features_at(self, coords) -> torch.Tensor:
        """Features at other coordinates (N×4 tensor, a CoordinateSet or a SparseTensor of the same
        stride); zero rows where this tensor has no voxel. Differentiable."""
        if isinstance(coords, SparseTensor):
            coords = coords.cset
        if isinstance(coords, CoordinateSet):
            if coords is self.cset:
                return self.feats
            coords = coords.coords
        idx = self.cset.lookup(coords.to(self.device))
        padded = torch.cat([self.feats, self.feats.new_zeros(1, self.num_channels)])
        return padded[torch.where(idx < 0, torch.full_like(idx, len(self)), idx)]

    @classmethod
    def from_voxels(cls, voxels, features, device=None, dtype=torch.float32) -> "SparseTensor":
        """Batch one or several :class:`stages.core.voxels.SparseVoxels` (same voxel size and origin).

        ``features``: a list of feature names (stacked as channels) or a callable ``voxels -> N×C``.
        """
        voxels = list(voxels) if isinstance(voxels, (list, tuple)) else [voxels]
        vs, org = voxels[0].voxel_size, voxels[0].origin
        coords, feats = [], []
        for b, v in enumerate(voxels):
            if v.voxel_size != vs or not np.allclose(v.origin, org):
                raise ValueError("all voxel sets in a batch must share voxel size and origin")
            c = np.concatenate([np.full((len(v), 1), b, np.int64), v.coords.astype(np.int64)], 1)
            coords.append(c)
            if callable(features):
                f = np.asarray(features(v), dtype=np.float64).reshape(len(v), -1)
            else:
                f = np.stack([np.asarray(v.features[n], dtype=np.float64).reshape(len(v)) for n in features], 1)
            feats.append(f)
        c = torch.from_numpy(np.concatenate(coords)).to(device)
        f = torch.from_numpy(np.concatenate(feats)).to(device=device, dtype=dtype)
        return cls(c, f, 1, vs, org)


# ---------------------------------------------------------------------- set algebra (union)
def _check_compatible(tensors):
    t0 = tensors[0]
    for t in tensors[1:]:
        if t.stride != t0.stride or t.voxel_size != t0.voxel_size or t.origin != t0.origin:
            raise ValueError("sparse tensors differ in stride, voxel size or origin")


def _union_set(tensors) -> tuple[CoordinateSet, list[torch.Tensor]]:
    """Union of the tensors' coordinate sets and each tensor's row index into it."""
    keys = torch.cat([t.cset.sorted_keys for t in tensors])
    ukeys = torch.unique(keys, sorted=True)
    out = CoordinateSet(unpack_keys(ukeys), tensors[0].stride, _sorted_keys=ukeys, _check=False)
    return out, [torch.searchsorted(ukeys, pack_keys(t.coords)) for t in tensors]


def union(*tensors: SparseTensor) -> SparseTensor:
    """Sum of tensors over the union of their coordinates (absent sites count as zero)."""
    _check_compatible(tensors)
    if all(t.cset is tensors[0].cset for t in tensors):
        return tensors[0].replace(sum(t.feats for t in tensors))
    cset, rows = _union_set(tensors)
    out = tensors[0].feats.new_zeros(len(cset), tensors[0].num_channels)
    for t, r in zip(tensors, rows):
        out = out.index_add(0, r, t.feats)
    return SparseTensor(feats=out, voxel_size=tensors[0].voxel_size, origin=tensors[0].origin, coordinate_set=cset)

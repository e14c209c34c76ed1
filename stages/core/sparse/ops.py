"""Functional sparse operations: convolutions (custom autograd), set algebra, dense conversion, sampling.

Convolution scheme ("gather-GEMM"): for each output row the features of its K kernel neighbours are
gathered into one row of an ``[n, K*C_in]`` matrix (missing neighbours read an appended zero row) and
multiplied once by the ``[K*C_in, C_out]`` weight. Rows are processed in chunks so the gathered matrix
stays a few MB (memory ∝ active voxels, not ∝ K × voxels). Backward never scatters:

* submanifold: the neighbour relation is symmetric (j is i's neighbour at offset o ⇔ i is j's at −o),
  so the input gradient is the same gather-GEMM on the output gradient with the kernel flipped and
  transposed, reusing the forward table;
* strided (kernel = stride) and transposed convolutions are each other's adjoint: one gathers the
  ≤F³ children of each coarse voxel, the other expands ``x @ W`` to ``[M, F³, C]`` and picks each fine
  voxel's octant.

A per-offset "pair" scheme (gather valid pairs, ``index_add_``) is kept as :func:`subm_conv_pairs`,
a reference for the tests; it was slower here (``git show 20a0cd9:docs/benchmarks/sparse.md``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .tensor import CoordinateSet, SparseTensor, _check_compatible, _union_set, pack_keys
from .tensor import union  # noqa: F401 (re-exported here: ops.union, as before)

# Rows per chunk are chosen so a gathered chunk holds about this many elements (≈ 1 MB in float32):
# large enough for an efficient GEMM, small enough to stay in cache (1 MB beat 256 kB, 4 MB and 16 MB
# on the 100k-voxel benchmark).
CHUNK_ELEMENTS = 1 << 18
# On a GPU the small chunks left the step launch-bound (thousands of tiny gathers and GEMMs: 0.61 s per
# training step on an H100 of which 0.18 s ran on the GPU); a chunk of up to 64 M elements (256 MB) makes a
# layer a handful of launches (docs/benchmarks/gpu.md).
CHUNK_ELEMENTS_CUDA = 1 << 26


def _chunk_rows(width: int, device: torch.device | None = None) -> int:
    budget = CHUNK_ELEMENTS_CUDA if device is not None and device.type == "cuda" else CHUNK_ELEMENTS
    return max(256, budget // max(width, 1))


def _padded(x: torch.Tensor) -> torch.Tensor:
    return torch.cat([x, x.new_zeros(1, x.shape[1])])


def gather_gemm(x: torch.Tensor, table: torch.Tensor, w2d: torch.Tensor,
                accumulate: torch.Tensor | None = None) -> torch.Tensor:
    """``out[i] = concat_k(x_pad[table[i, k]]) @ w2d`` with ``x_pad = [x; 0]``; chunked.
    With ``accumulate`` (no autograd) the product is added into that tensor, which is returned."""
    n, k = table.shape
    c = x.shape[1]
    xp = _padded(x)
    out = x.new_empty(n, w2d.shape[1]) if accumulate is None else accumulate
    rows = _chunk_rows(k * c, x.device)
    for s in range(0, n, rows):
        g = xp.index_select(0, table[s : s + rows].reshape(-1)).view(-1, k * c)
        if accumulate is None:
            torch.mm(g, w2d, out=out[s : s + rows])
        else:
            out[s : s + rows].addmm_(g, w2d)
    return out


def gather_t_gemm(x: torch.Tensor, table: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """``sum_i concat_k(x_pad[table[i, k]])ᵀ ⊗ g[i]`` → ``[K*C, C_out]`` (weight gradient); chunked."""
    n, k = table.shape
    c = x.shape[1]
    xp = _padded(x)
    out = x.new_zeros(k * c, g.shape[1])
    rows = _chunk_rows(k * c, x.device)
    for s in range(0, n, rows):
        gx = xp.index_select(0, table[s : s + rows].reshape(-1)).view(-1, k * c)
        out.addmm_(gx.t(), g[s : s + rows])
    return out


def _expand_gemm(x: torch.Tensor, wcat: torch.Tensor, k: int, flat: torch.Tensor) -> torch.Tensor:
    """``[x @ wcat viewed as (M*K) × C_out ; 0]`` rows ``flat`` (each fine voxel picks its octant)."""
    c_out = wcat.shape[1] // k
    y = torch.mm(x, wcat).view(-1, c_out)
    return _padded(y).index_select(0, flat)


class _SubmConvFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, table):
        k, c_in, c_out = weight.shape
        ctx.save_for_backward(x, weight, table)
        return gather_gemm(x, table, weight.reshape(k * c_in, c_out))

    @staticmethod
    def backward(ctx, g):
        x, weight, table = ctx.saved_tensors
        k, c_in, c_out = weight.shape
        g = g.contiguous()
        gx = gw = None
        if ctx.needs_input_grad[0]:
            w_back = weight.flip(0).transpose(1, 2).reshape(k * c_out, c_in)
            gx = gather_gemm(g, table, w_back)
        if ctx.needs_input_grad[1]:
            gw = gather_t_gemm(x, table, g).view(k, c_in, c_out)
        return gx, gw, None


class _DownConvFn(torch.autograd.Function):
    """Fine → coarse, kernel = stride: ``out[j] = Σ_o x[child[j, o]] @ W[o]``."""

    @staticmethod
    def forward(ctx, x, weight, child, flat_parent):
        k, c_in, c_out = weight.shape
        ctx.save_for_backward(x, weight, child, flat_parent)
        return gather_gemm(x, child, weight.reshape(k * c_in, c_out))

    @staticmethod
    def backward(ctx, g):
        x, weight, child, flat_parent = ctx.saved_tensors
        k, c_in, c_out = weight.shape
        g = g.contiguous()
        gx = gw = None
        if ctx.needs_input_grad[0]:
            wcat = weight.permute(2, 0, 1).reshape(c_out, k * c_in)
            gx = _expand_gemm(g, wcat, k, flat_parent)
        if ctx.needs_input_grad[1]:
            gw = gather_t_gemm(x, child, g).view(k, c_in, c_out)
        return gx, gw, None, None


class _UpConvFn(torch.autograd.Function):
    """Coarse → fine, kernel = stride: ``out[i] = x[parent(i)] @ W[octant(i)]`` (adjoint of down)."""

    @staticmethod
    def forward(ctx, x, weight, child, flat_parent):
        k, c_in, c_out = weight.shape
        ctx.save_for_backward(x, weight, child, flat_parent)
        wcat = weight.permute(1, 0, 2).reshape(c_in, k * c_out)
        return _expand_gemm(x, wcat, k, flat_parent)

    @staticmethod
    def backward(ctx, g):
        x, weight, child, flat_parent = ctx.saved_tensors
        k, c_in, c_out = weight.shape
        g = g.contiguous()
        gx = gw = None
        if ctx.needs_input_grad[0]:
            gx = gather_gemm(g, child, weight.transpose(1, 2).reshape(k * c_out, c_in))
        if ctx.needs_input_grad[1]:
            # Σ_i x[parent(i)]ᵀ g[i] per octant = xᵀ · (children's gradients side by side)
            gcat = gather_t_gemm(g, child, x)  # [K*C_out, C_in]
            gw = gcat.view(k, c_out, c_in).transpose(1, 2)
        return gx, gw, None, None


# ---------------------------------------------------------------------- convolution entry points
def subm_conv(x: SparseTensor, weight: torch.Tensor, bias: torch.Tensor | None = None,
              accumulate: torch.Tensor | None = None) -> SparseTensor:
    """Submanifold convolution: output on the input coordinates. ``weight`` is K×C_in×C_out with
    offsets in :func:`stages.core.sparse.tensor.kernel_offsets` order (K = k³, k odd). With ``accumulate``
    (an N×C_out tensor, no autograd) the result is added into that tensor instead of a new one."""
    k = weight.shape[0]
    ks = round(k ** (1 / 3))
    if ks**3 != k:
        raise ValueError(f"weight must have k³ offsets, got {k}")
    if accumulate is not None:
        if torch.is_grad_enabled():
            raise RuntimeError("subm_conv(accumulate=...) writes in place: use it without gradients")
        if ks == 1:
            out = accumulate.addmm_(x.feats, weight[0])
        else:
            out = gather_gemm(x.feats, x.cset.neighbour_map(ks), weight.reshape(k * weight.shape[1], -1), accumulate)
    elif ks == 1:
        out = x.feats @ weight[0]
    else:
        out = _SubmConvFn.apply(x.feats, weight, x.cset.neighbour_map(ks))
    if bias is not None:
        out = out + bias
    return x.replace(out)


def subm_conv_parts(parts, weight: torch.Tensor, bias: torch.Tensor | None = None) -> SparseTensor:
    """:func:`subm_conv` of the channel concatenation of ``parts`` (tensors on one coordinate set),
    computed as the sum of each part's convolution with its slice of input channels, so the
    concatenated features are never held in memory (nor saved for backward)."""
    parts = tuple(parts)
    if any(t.cset is not parts[0].cset for t in parts[1:]):
        raise ValueError("subm_conv_parts needs tensors on one coordinate set")
    widths = [t.num_channels for t in parts]
    if sum(widths) != weight.shape[1]:
        raise ValueError(f"parts have {sum(widths)} channels, the weight expects {weight.shape[1]}")
    out, start = None, 0
    for t, c in zip(parts, widths):
        w = weight[:, start : start + c]
        start += c
        if out is None:
            out = subm_conv(t, w).feats
        elif torch.is_grad_enabled():
            out = out + subm_conv(t, w).feats
        else:  # inference: accumulate straight into the first part's fresh output
            subm_conv(t, w, accumulate=out)
    if bias is not None:
        out = out + bias
    return parts[0].replace(out)


def subm_conv_pairs(x: SparseTensor, weight: torch.Tensor) -> SparseTensor:
    """Reference per-offset pair scheme (autograd through ``index_add``); for the tests."""
    k = weight.shape[0]
    table = x.cset.neighbour_map(round(k ** (1 / 3)))
    n = len(x)
    cache = x.cset._cache.setdefault(("pairs", k), [])
    if not cache:
        for o in range(k):
            col = table[:, o]
            out_idx = torch.nonzero(col < n).squeeze(1)
            cache.append((out_idx, col[out_idx]))
    out = x.feats.new_zeros(n, weight.shape[2])
    for o, (out_idx, in_idx) in enumerate(cache):
        out = out.index_add(0, out_idx, x.feats[in_idx] @ weight[o])
    return x.replace(out)


def down_conv(x: SparseTensor, weight: torch.Tensor, factor: int = 2, bias=None) -> SparseTensor:
    """Strided convolution with kernel = stride = ``factor``; output on the (cached) coarse set."""
    coarse = x.cset.downsample(factor)
    flat_parent, child = x.cset.transfer_maps(coarse)
    out = _DownConvFn.apply(x.feats, weight, child, flat_parent)
    if bias is not None:
        out = out + bias
    return SparseTensor(feats=out, voxel_size=x.voxel_size, origin=x.origin, coordinate_set=coarse)


def up_conv(x: SparseTensor, weight: torch.Tensor, target: SparseTensor | CoordinateSet | None = None,
            bias=None) -> SparseTensor:
    """Transposed convolution with kernel = stride onto a finer coordinate set: ``target`` (a tensor or
    set), by default the set ``x`` was downsampled from. Fine voxels without a coarse parent get 0."""
    fine = target.cset if isinstance(target, SparseTensor) else target
    if fine is None:
        fine = x.cset.parent
        if fine is None:
            raise ValueError("up_conv needs a target: this tensor was not made by downsampling")
    k = weight.shape[0]
    if (x.stride // fine.stride) ** 3 != k:
        raise ValueError(f"weight has {k} offsets but stride ratio is {x.stride // fine.stride}")
    flat_parent, child = fine.transfer_maps(x.cset)
    out = _UpConvFn.apply(x.feats, weight, child, flat_parent)
    if bias is not None:
        out = out + bias
    return SparseTensor(feats=out, voxel_size=x.voxel_size, origin=x.origin, coordinate_set=fine)


# ---------------------------------------------------------------------- set algebra
# union and the helpers cat shares live in .tensor, beside SparseTensor.__add__ that uses union


def intersection(a: SparseTensor, b: SparseTensor) -> SparseTensor:
    """``a``'s features restricted to the coordinates present in both ``a`` and ``b``."""
    _check_compatible([a, b])
    if a.cset is b.cset:
        return a
    keep = torch.nonzero(b.cset.lookup_keys(pack_keys(a.coords)) >= 0).squeeze(1)
    cset = CoordinateSet(a.coords[keep], a.stride, _check=False)
    return SparseTensor(feats=a.feats[keep], voxel_size=a.voxel_size, origin=a.origin, coordinate_set=cset)


def cat(*tensors: SparseTensor) -> SparseTensor:
    """Channel concatenation. On different coordinate sets the result lives on their union, each
    tensor contributing zeros where it has no voxel."""
    _check_compatible(tensors)
    if all(t.cset is tensors[0].cset for t in tensors):
        return tensors[0].replace(torch.cat([t.feats for t in tensors], 1))
    cset, rows = _union_set(tensors)
    parts = []
    for t, r in zip(tensors, rows):
        parts.append(t.feats.new_zeros(len(cset), t.num_channels).index_copy(0, r, t.feats))
    return SparseTensor(feats=torch.cat(parts, 1), voxel_size=tensors[0].voxel_size, origin=tensors[0].origin,
                        coordinate_set=cset)


# ---------------------------------------------------------------------- dense conversion
def to_dense(x: SparseTensor, offset=None, shape=None, batch_size: int | None = None):
    """Dense ``[B, C, X, Y, Z]`` tensor (zeros at inactive sites) and ``offset``, the stride-1
    coordinate of element ``[..., 0, 0, 0]``; neighbouring elements are ``stride`` apart. Differentiable.
    Voxels outside ``shape`` are dropped."""
    s = x.stride
    lat = torch.div(x.coords[:, 1:], s, rounding_mode="floor")
    if offset is None:
        lo = lat.min(0).values if len(x) else torch.zeros(3, dtype=torch.long, device=x.device)
    else:
        lo = torch.div(torch.as_tensor(offset, device=x.device).long(), s, rounding_mode="floor")
    idx = lat - lo
    if shape is None:
        shape = tuple((idx.max(0).values + 1).tolist()) if len(x) else (1, 1, 1)
    shape = tuple(int(v) for v in shape)
    b = x.coords[:, 0]
    if batch_size is None:
        batch_size = int(b.max()) + 1 if len(x) else 1
    inside = ((idx >= 0) & (idx < torch.tensor(shape, device=x.device))).all(1) & (b < batch_size)
    sel = torch.nonzero(inside).squeeze(1)
    dense = x.feats.new_zeros(batch_size, *shape, x.num_channels)
    i = idx[sel]
    dense = dense.index_put((b[sel], i[:, 0], i[:, 1], i[:, 2]), x.feats[sel])
    return dense.permute(0, 4, 1, 2, 3), lo * s


def from_dense(dense: torch.Tensor, mask: torch.Tensor | None = None, offset=(0, 0, 0), stride: int = 1,
               voxel_size: float = 1.0, origin=(0.0, 0.0, 0.0)) -> SparseTensor:
    """Sparse tensor of the active sites of ``dense`` ``[B, C, X, Y, Z]``: ``mask`` ``[B, X, Y, Z]``
    (default: any channel non-zero). Element ``[b, :, i, j, k]`` gets coordinate
    ``offset + (i, j, k) * stride``. Differentiable with respect to ``dense``."""
    if dense.ndim != 5:
        raise ValueError("dense must be [B, C, X, Y, Z]")
    if mask is None:
        mask = (dense != 0).any(1)
    nz = torch.nonzero(mask)
    feats = dense.permute(0, 2, 3, 4, 1)[nz[:, 0], nz[:, 1], nz[:, 2], nz[:, 3]]
    coords = nz.clone()
    coords[:, 1:] = nz[:, 1:] * stride + torch.as_tensor(offset, device=dense.device).long()
    return SparseTensor(coords, feats, stride, voxel_size, origin)


# ---------------------------------------------------------------------- sampling at world points
def sample_at(x: SparseTensor, points: torch.Tensor, batch: torch.Tensor | int = 0, mode: str = "trilinear",
              renormalize: bool = False) -> torch.Tensor:
    """Features at arbitrary world points (P×3 mm) → P×C.

    ``trilinear`` interpolates between the 8 surrounding voxel centres, absent voxels counting as
    zero — exactly ``grid_sample(align_corners=True, padding_mode="zeros")`` on the dense grid; with
    ``renormalize=True`` the weights of present corners are rescaled to sum to one instead (points with
    no present corner get 0). ``nearest`` takes the closest voxel centre (0 if absent).
    Differentiable with respect to the features and, for trilinear, the points.
    """
    if mode not in ("trilinear", "nearest"):
        raise ValueError(f"mode must be 'trilinear' or 'nearest', got {mode!r}")
    s = x.stride
    pts = points.to(device=x.device)
    dtype = x.feats.dtype if x.feats.dtype.is_floating_point else torch.float32
    origin = torch.tensor(x.origin, dtype=pts.dtype if pts.dtype.is_floating_point else dtype, device=x.device)
    # lattice coordinate: voxel centres (c + (s-1)/2) sit at integers after dividing by s
    u = ((pts - origin) / x.voxel_size - (s - 1) / 2.0) / s
    p = pts.shape[0]
    b = torch.as_tensor(batch, device=x.device).long().expand(p)
    padded = _padded(x.feats)
    n = len(x)

    def rows(lat):
        c = torch.cat([b[:, None], lat * s], 1)
        r = x.cset.lookup(c)
        return torch.where(r < 0, torch.full_like(r, n), r)

    if mode == "nearest":
        return padded[rows(torch.round(u.detach()).long())]
    base = torch.floor(u.detach())
    frac = (u - base).to(dtype)
    base = base.long()
    out = x.feats.new_zeros(p, x.num_channels)
    wsum = x.feats.new_zeros(p, 1)
    for corner in range(8):
        d = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], device=x.device)
        w = torch.where(d.bool(), frac, 1 - frac).prod(1, keepdim=True)
        r = rows(base + d)
        if renormalize:
            wsum = wsum + w * (r < n).to(w.dtype)[:, None]
        out = out + w * padded[r]
    if renormalize:
        out = torch.where(wsum > 0, out / wsum.clamp_min(1e-12), torch.zeros_like(out))
    return out

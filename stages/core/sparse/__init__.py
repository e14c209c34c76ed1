"""Sparse 3D tensors and layers in pure PyTorch (CPU and CUDA, no compiled extension).

Reads and writes nothing on disk: this is the in-memory layer the SBP network runs on. On-disk voxel
sets are :class:`stages.core.voxels.SparseVoxels`; :meth:`SparseTensor.from_voxels` batches them.

Public API::

    x = SparseTensor(coords, feats, stride=1, voxel_size=0.5, origin=(0, 0, 0))
        # coords: N×4 int (batch, x, y, z) or N×3 (batch 0), in stride-1 voxel units;
        # feats: N×C. Voxel c of a stride-s tensor is centred at origin + (c + (s-1)/2) * voxel_size.
    x.replace(feats), x.to(device), x.world_points(), x.features_at(coords_or_tensor),
    SparseTensor.from_voxels([SparseVoxels, ...], ["occupancy", ...])

    SubmConv3d(c_in, c_out, kernel_size=3)       # kernel 1, 3 or 5; output on the input coordinates
    StridedConv3d(c_in, c_out, kernel_size=2)     # kernel = stride; to the cached coarser set
    TransposedConv3d(c_in, c_out, kernel_size=2)  # forward(x, target=None): back onto the finer set
    SparseBatchNorm(c), SparseReLU(), SparseELU()
    cat(a, b, ...), union(a, b, ...), intersection(a, b)
    to_dense(x) -> (dense [B, C, X, Y, Z], offset), from_dense(dense, mask=None, offset=..., stride=...)
    sample_at(x, points_mm, batch=0, mode="trilinear" | "nearest")
    SparseUNet(in_channels, out_channels, widths=(16, 32, 64, 96), blocks=(1, 2, 2, 2))

Design: coordinates are hashed as sorted 64-bit keys searched with ``torch.searchsorted``; each
:class:`CoordinateSet` caches its neighbour table (per kernel size) and its parent/child maps to
coarser sets, and layers pass the same set object along, so nothing is rebuilt inside a network.
Convolutions gather each output's neighbour features into one matrix row and multiply once per chunk
of rows (custom autograd functions; the backward pass is gathers and GEMMs too, no atomic scatter).
See :mod:`stages.core.sparse.ops` for the scheme and docs/benchmarks/sparse.md for measured speed.

``SPARSE_UNET_SBP_DEFAULT`` is the configuration suggested for CPU training of the SBP network.
"""

from .nn import (
    ResidualBlock,
    SparseBatchNorm,
    SparseELU,
    SparseReLU,
    SparseSequential,
    SparseUNet,
    StridedConv3d,
    SubmConv3d,
    TransposedConv3d,
)
from .ops import (cat, down_conv, from_dense, intersection, sample_at, subm_conv, subm_conv_parts, to_dense, union,
                  up_conv)
from .tensor import CoordinateSet, SparseTensor, kernel_offsets

# Suggested SBP network on 2 CPU cores (~26 input channels, 2 outputs, ~100k voxels per sample);
# timing and memory in docs/benchmarks/sparse.md.
SPARSE_UNET_SBP_DEFAULT = dict(widths=(16, 32, 64, 96), blocks=(1, 2, 2, 2))

__all__ = [
    "CoordinateSet",
    "ResidualBlock",
    "SPARSE_UNET_SBP_DEFAULT",
    "SparseBatchNorm",
    "SparseELU",
    "SparseReLU",
    "SparseSequential",
    "SparseTensor",
    "SparseUNet",
    "StridedConv3d",
    "SubmConv3d",
    "TransposedConv3d",
    "cat",
    "down_conv",
    "from_dense",
    "intersection",
    "kernel_offsets",
    "sample_at",
    "subm_conv",
    "subm_conv_parts",
    "to_dense",
    "union",
    "up_conv",
]

"""Sparse layers (``torch.nn.Module``s on :class:`SparseTensor`) and the residual sparse U-Net."""

from __future__ import annotations

import math

import torch
from torch import nn

from . import ops
from .tensor import SparseTensor


def _init_weight(k: int, c_in: int, c_out: int) -> nn.Parameter:
    # Kaiming-uniform over the full fan-in (k * c_in), as nn.Conv3d does
    bound = 1.0 / math.sqrt(k * c_in) * math.sqrt(3.0) * math.sqrt(2.0 / (1 + 5))
    return nn.Parameter(torch.empty(k, c_in, c_out).uniform_(-bound, bound))


class _Conv(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, k: int, bias: bool):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.weight = _init_weight(k, in_channels, out_channels)
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={self.bias is not None}"


class SubmConv3d(_Conv):
    """Submanifold convolution (odd ``kernel_size``: 1, 3, 5): output on the input coordinates.

    ``weight[o, c_in, c_out]`` with offsets in ``kernel_offsets`` order; dense equivalent
    ``conv3d(padding=k//2)`` with weight ``w[c_out, c_in, a, b, c] = weight[(a*k + b)*k + c, c_in, c_out]``.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False):
        if kernel_size % 2 != 1:
            raise ValueError("SubmConv3d needs an odd kernel size")
        self.kernel_size = kernel_size
        super().__init__(in_channels, out_channels, kernel_size**3, bias)

    def forward(self, x: SparseTensor | tuple[SparseTensor, ...]) -> SparseTensor:
        """``x``: a tensor, or a tuple of tensors on one coordinate set standing for their channel
        concatenation (convolved part by part, so the concatenation is never materialised)."""
        if isinstance(x, tuple):
            return ops.subm_conv_parts(x, self.weight, self.bias)
        return ops.subm_conv(x, self.weight, self.bias)


class StridedConv3d(_Conv):
    """Convolution with kernel = stride (default 2) onto the coarser coordinate set covering the input.

    Dense equivalent ``conv3d(kernel_size=2, stride=2)`` on a grid aligned to multiples of the output
    stride; weight offsets are ``(a, b, c)`` in 0..k-1, flattened as in ``SubmConv3d``.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int | None = None,
                 bias: bool = False):
        stride = kernel_size if stride is None else stride
        if stride != kernel_size:
            raise ValueError("only kernel_size == stride is supported")
        self.kernel_size = kernel_size
        super().__init__(in_channels, out_channels, kernel_size**3, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        return ops.down_conv(x, self.weight, self.kernel_size, self.bias)


class TransposedConv3d(_Conv):
    """Transposed convolution with kernel = stride (default 2) back onto a finer coordinate set.

    ``forward(x, target=None)``: ``target`` (tensor or coordinate set) defaults to the set ``x`` was
    downsampled from, so a decoder lands exactly on the encoder's cached coordinates. Dense equivalent
    ``conv_transpose3d(kernel_size=2, stride=2)`` restricted to the target sites.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int | None = None,
                 bias: bool = False):
        stride = kernel_size if stride is None else stride
        if stride != kernel_size:
            raise ValueError("only kernel_size == stride is supported")
        self.kernel_size = kernel_size
        super().__init__(in_channels, out_channels, kernel_size**3, bias)
        # fan-in of a transposed conv is c_in (each output sees one input voxel)
        bound = math.sqrt(3.0 / in_channels) * math.sqrt(2.0 / (1 + 5))
        nn.init.uniform_(self.weight, -bound, bound)

    def forward(self, x: SparseTensor, target=None) -> SparseTensor:
        return ops.up_conv(x, self.weight, target, self.bias)


def _column_mean_var(f: torch.Tensor, rows: int = 32768) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel mean and biased variance of an N×C tensor, accumulated in float64 over row chunks:
    2-3× faster on CPU than ``torch.var_mean(f, 0)`` (a strided column reduction), and exact enough
    for the E[x²] − E[x]² form."""
    s = f.new_zeros(f.shape[1], dtype=torch.float64)
    ss = f.new_zeros(f.shape[1], dtype=torch.float64)
    for i in range(0, len(f), rows):
        c = f[i : i + rows]
        s += c.sum(0, dtype=torch.float64)
        ss += (c * c).sum(0, dtype=torch.float64)
    mean = s / len(f)
    var = (ss / len(f) - mean * mean).clamp_(min=0.0)
    return mean.to(f.dtype), var.to(f.dtype)


class SparseBatchNorm(nn.BatchNorm1d):
    """Batch norm over the active voxels' features (inactive sites do not count).

    ``inplace=True`` lets it normalise its input's features in place when no gradient is recorded and
    it keeps no running statistics (SBP inference), for layers that own their input (a convolution's
    fresh output): at 1 M voxels × 32 channels that saves a 140 MB copy per layer. With gradients it
    always makes a new tensor, since the backward pass needs the input.
    """

    def __init__(self, num_features: int, *args, inplace: bool = False, **kwargs):
        super().__init__(num_features, *args, **kwargs)
        self.inplace = inplace

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        f = x.feats
        # only without running statistics (none to update), so the two paths compute the same thing
        if self.inplace and self.running_mean is None and not torch.is_grad_enabled() and len(f) > 1:
            mean, var = _column_mean_var(f)
            scale = torch.rsqrt(var + self.eps)
            if self.affine:
                scale *= self.weight
            shift = -mean * scale
            if self.affine:
                shift += self.bias
            f.mul_(scale).add_(shift)
            return x
        return x.replace(super().forward(f))


class SparseReLU(nn.ReLU):
    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace(super().forward(x.feats))


class SparseELU(nn.ELU):
    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace(super().forward(x.feats))


class SparseSequential(nn.Sequential):
    pass


def conv_bn_act(c_in: int, c_out: int, kernel_size: int = 3) -> SparseSequential:
    return SparseSequential(SubmConv3d(c_in, c_out, kernel_size), SparseBatchNorm(c_out, inplace=True),
                            SparseReLU(inplace=True))


class ResidualBlock(nn.Module):
    """Two kernel-3 submanifold convolutions with batch norm, ReLU and an identity (or 1×1) shortcut.

    The input may be a tuple of tensors on one coordinate set, meaning their channel concatenation
    (a decoder's upsampled features and skip), which is then never materialised."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv1 = SubmConv3d(c_in, c_out, 3)
        self.bn1 = SparseBatchNorm(c_out, inplace=True)
        self.conv2 = SubmConv3d(c_out, c_out, 3)
        self.bn2 = SparseBatchNorm(c_out, inplace=True)
        self.act = SparseReLU(inplace=True)
        self.shortcut = (None if c_in == c_out
                         else SparseSequential(SubmConv3d(c_in, c_out, 1), SparseBatchNorm(c_out, inplace=True)))

    def forward(self, x: SparseTensor | tuple[SparseTensor, ...]) -> SparseTensor:
        y = self.act(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        if self.shortcut is None:
            skip = ops.cat(*x) if isinstance(x, tuple) else x
        else:
            skip = self.shortcut(x)
        if torch.is_grad_enabled():
            return self.act(y.replace(y.feats + skip.feats))
        y.feats.add_(skip.feats)  # inference: y is bn2's own output, so add in place
        return self.act(y)


class SparseUNet(nn.Module):
    """Residual sparse U-Net (MinkUNet-style).

    * stem: kernel-``stem_kernel`` submanifold conv ``in_channels → widths[0]`` + BN + ReLU, then
      ``blocks[0]`` residual blocks;
    * encoder level ``l = 1..L-1``: kernel-2 stride-2 conv ``widths[l-1] → widths[l]`` + BN + ReLU, then
      ``blocks[l]`` residual blocks;
    * decoder level ``l = L-1..1``: transposed conv ``→ dec_widths[l-1]`` onto level ``l-1``'s cached
      coordinates + BN + ReLU, concatenation with the encoder's level-``l-1`` features, then
      ``dec_blocks[l-1]`` residual blocks;
    * head: 1×1 submanifold conv (with bias) to ``out_channels``.

    Output lives on the input coordinates. ``widths``/``blocks`` set depth and width;
    ``dec_widths`` defaults to ``widths[:-1]`` and ``dec_blocks`` to ``blocks[:-1]``.
    """

    def __init__(self, in_channels: int, out_channels: int, widths=(16, 32, 64, 96), blocks=(1, 2, 2, 2),
                 dec_widths=None, dec_blocks=None, stem_kernel: int = 3):
        super().__init__()
        widths, blocks = tuple(widths), tuple(blocks)
        if len(blocks) != len(widths):
            raise ValueError("blocks needs one entry per level")
        levels = len(widths)
        dec_widths = tuple(widths[:-1] if dec_widths is None else dec_widths)
        dec_blocks = tuple(blocks[:-1] if dec_blocks is None else dec_blocks)
        if len(dec_widths) != levels - 1 or len(dec_blocks) != levels - 1:
            raise ValueError("dec_widths and dec_blocks need one entry per decoder level (levels - 1)")
        self.config = dict(in_channels=in_channels, out_channels=out_channels, widths=widths, blocks=blocks,
                           dec_widths=dec_widths, dec_blocks=dec_blocks, stem_kernel=stem_kernel)
        self.stem = SparseSequential(conv_bn_act(in_channels, widths[0], stem_kernel),
                                     *[ResidualBlock(widths[0], widths[0]) for _ in range(blocks[0])])
        self.down = nn.ModuleList()
        for lvl in range(1, levels):
            self.down.append(SparseSequential(
                StridedConv3d(widths[lvl - 1], widths[lvl], 2), SparseBatchNorm(widths[lvl], inplace=True),
                SparseReLU(inplace=True),
                *[ResidualBlock(widths[lvl], widths[lvl]) for _ in range(blocks[lvl])]))
        self.up = nn.ModuleList()
        self.up_bn = nn.ModuleList()
        self.dec = nn.ModuleList()
        for lvl in range(levels - 1, 0, -1):
            below = widths[lvl] if lvl == levels - 1 else dec_widths[lvl]
            c = dec_widths[lvl - 1]
            self.up.append(TransposedConv3d(below, c, 2))
            self.up_bn.append(SparseSequential(SparseBatchNorm(c, inplace=True), SparseReLU(inplace=True)))
            blocks_here = [ResidualBlock(c + widths[lvl - 1], c)]
            blocks_here += [ResidualBlock(c, c) for _ in range(dec_blocks[lvl - 1] - 1)]
            self.dec.append(SparseSequential(*blocks_here) if dec_blocks[lvl - 1] > 0
                            else SparseSequential(SubmConv3d(c + widths[lvl - 1], c, 1)))
        self.head = SubmConv3d(dec_widths[0] if levels > 1 else widths[0], out_channels, 1, bias=True)

    def forward(self, x: SparseTensor) -> SparseTensor:
        skips = [self.stem(x)]
        for layer in self.down:
            skips.append(layer(skips[-1]))
        y = skips.pop()
        for up, bn, dec in zip(self.up, self.up_bn, self.dec):
            skip = skips.pop()
            y = bn(up(y, skip))
            y = dec((y, skip))  # the channel concatenation, convolved part by part
        return self.head(y)

"""Exactness of the sparse layers against their dense PyTorch equivalents (restricted to active sites)."""

import pytest
import torch
import torch.nn.functional as F

from stages.core.sparse import (
    CoordinateSet,
    SparseBatchNorm,
    SparseELU,
    SparseReLU,
    SparseTensor,
    SparseUNet,
    StridedConv3d,
    SubmConv3d,
    TransposedConv3d,
    cat,
    from_dense,
    intersection,
    kernel_offsets,
    sample_at,
    to_dense,
    union,
)
from stages.core.sparse import ops
from stages.core.sparse.tensor import pack_keys, unpack_keys

TOL = 1e-4


def random_grid(seed, d=8, c=3, density=0.4, batch=1, dtype=torch.float32):
    """Dense [B, C, d, d, d] features, zero outside a random mask, and the mask."""
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(batch, d, d, d, generator=g) < density
    x = torch.randn(batch, c, d, d, d, generator=g, dtype=dtype) * mask[:, None]
    return x, mask


def at_mask(dense, mask):
    """[B, C, X, Y, Z] → N×C rows at mask, in from_dense's row order."""
    return dense.permute(0, 2, 3, 4, 1)[mask]


def dense_subm_weight(weight, k):
    return weight.permute(2, 1, 0).reshape(weight.shape[2], weight.shape[1], k, k, k)


# ---------------------------------------------------------------------- hashing
def test_keys_roundtrip_and_order():
    g = torch.Generator().manual_seed(1)
    c = torch.randint(-60000, 60000, (500, 4), generator=g)
    c[:, 0] = torch.randint(0, 4000, (500,), generator=g)
    assert torch.equal(unpack_keys(pack_keys(c)), c)
    # key order is lexicographic (b, x, y, z)
    order = torch.argsort(pack_keys(c))
    cs = c[order].tolist()
    assert cs == sorted(cs)


def test_lookup_and_duplicates():
    coords = torch.tensor([[0, 1, 2, 3], [0, -5, 0, 7], [1, 1, 2, 3]])
    cs = CoordinateSet(coords)
    q = torch.tensor([[1, 1, 2, 3], [0, 1, 2, 3], [0, 1, 2, 4], [2, 1, 2, 3], [0, -5, 0, 7]])
    assert cs.lookup(q).tolist() == [2, 0, -1, -1, 1]
    with pytest.raises(ValueError, match="duplicate"):
        CoordinateSet(torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]]))
    with pytest.raises(ValueError, match="multiples"):
        CoordinateSet(torch.tensor([[0, 1, 2, 4]]), stride=2)


def test_neighbour_map_matches_brute_force_and_is_cached():
    x, mask = random_grid(2, d=6)
    st = from_dense(x, mask, offset=(-3, 5, 0))
    table = st.cset.neighbour_map(3)
    assert st.cset.neighbour_map(3) is table
    coords = st.coords.tolist()
    where = {tuple(c): i for i, c in enumerate(coords)}
    offs = kernel_offsets(3).tolist()
    n = len(st)
    for i, c in enumerate(coords):
        for o, d in enumerate(offs):
            j = where.get((c[0], c[1] + d[0], c[2] + d[1], c[3] + d[2]), n)
            assert table[i, o] == j


# ---------------------------------------------------------------------- convolutions
@pytest.mark.parametrize("k", [1, 3, 5])
def test_subm_conv_matches_dense_forward_and_backward(k):
    xd, mask = random_grid(10 + k, d=9, c=4, batch=2)
    xd.requires_grad_(True)
    conv = SubmConv3d(4, 5, k, bias=True)
    with torch.no_grad():
        conv.bias.normal_()
    xs = from_dense(xd.detach(), mask, offset=(-4, 3, 1)).to(dtype=torch.float32)
    xs.feats.requires_grad_(True)
    out = conv(xs)
    ref = F.conv3d(xd, dense_subm_weight(conv.weight, k), conv.bias, padding=k // 2)
    ref_s = at_mask(ref, mask)
    assert out.feats.abs().max() > 0.1
    assert (out.feats - ref_s).abs().max() <= TOL
    r = torch.randn_like(ref_s)
    (gx, gw, gb) = torch.autograd.grad((out.feats * r).sum(), [xs.feats, conv.weight, conv.bias])
    (gxd, gwd, gbd) = torch.autograd.grad((ref_s * r).sum(), [xd, conv.weight, conv.bias])
    assert (gx - at_mask(gxd, mask)).abs().max() <= TOL
    assert (gw - gwd).abs().max() <= TOL * max(1.0, gwd.abs().max())
    assert (gb - gbd).abs().max() <= TOL * max(1.0, gbd.abs().max())


def test_subm_conv_pair_scheme_agrees():
    xd, mask = random_grid(5, d=8, c=3)
    xs = from_dense(xd, mask)
    w = torch.randn(27, 3, 4)
    assert (ops.subm_conv(xs, w).feats - ops.subm_conv_pairs(xs, w).feats).abs().max() <= TOL


def test_subm_conv_on_stride_2_set():
    # neighbours of a coarse set are 2 voxels apart: dense equivalent on the coarse lattice
    xd, mask = random_grid(6, d=6, c=3)
    xs = from_dense(xd, mask, offset=(-2, 0, 4), stride=2)
    w = torch.randn(27, 3, 2)
    ref = F.conv3d(xd, dense_subm_weight(w, 3), padding=1)
    assert (ops.subm_conv(xs, w).feats - at_mask(ref, mask)).abs().max() <= TOL


def test_strided_conv_matches_dense():
    xd, mask = random_grid(21, d=10, c=3, batch=2)
    xd.requires_grad_(True)
    xs = from_dense(xd.detach(), mask, offset=(-6, 2, 0))  # even offset: grid aligned to stride 2
    xs.feats.requires_grad_(True)
    conv = StridedConv3d(3, 4)
    out = conv(xs)
    assert out.stride == 2 and out.cset is xs.cset.downsample(2)
    ref = F.conv3d(xd, dense_subm_weight(conv.weight, 2), stride=2)
    coarse_mask = F.max_pool3d(mask[:, None].float(), 2)[:, 0] > 0
    dense_out, off = to_dense(out, offset=(-6, 2, 0), shape=(5, 5, 5), batch_size=2)
    assert off.tolist() == [-6, 2, 0]
    assert int(coarse_mask.sum()) == len(out)
    assert (at_mask(dense_out, coarse_mask) - at_mask(ref, coarse_mask)).abs().max() <= TOL
    # backward: compare via the dense-layout output
    r = torch.randn_like(ref)
    gx, gw = torch.autograd.grad((dense_out * r).sum(), [xs.feats, conv.weight])
    gxd, gwd = torch.autograd.grad((ref * r * coarse_mask[:, None]).sum(), [xd, conv.weight])
    assert (gx - at_mask(gxd, mask)).abs().max() <= TOL
    assert (gw - gwd).abs().max() <= TOL * max(1.0, gwd.abs().max())


@pytest.mark.parametrize("own_parent", [True, False])
def test_transposed_conv_matches_dense(own_parent):
    fd, fmask = random_grid(31, d=10, c=1, batch=2)
    fine = from_dense(fd, fmask, offset=(2, -4, 0))
    if own_parent:
        coarse_set = fine.cset.downsample(2)
    else:  # an unrelated coarse set: some fine voxels have no parent, some coarse voxels no child
        _, cmask = random_grid(32, d=5, c=1, batch=2, density=0.5)
        coarse_set = from_dense(torch.ones(2, 1, 5, 5, 5), cmask, offset=(2, -4, 0), stride=2).cset
    g = torch.Generator().manual_seed(3)
    xs = SparseTensor(feats=torch.randn(len(coarse_set), 4, generator=g), coordinate_set=coarse_set)
    xs.feats.requires_grad_(True)
    conv = TransposedConv3d(4, 3)
    out = conv(xs, fine) if not own_parent else conv(xs)
    assert out.cset is fine.cset
    xcd, _ = to_dense(xs, offset=(2, -4, 0), shape=(5, 5, 5), batch_size=2)
    xcd = xcd.detach().requires_grad_(True)
    w_t = conv.weight.permute(1, 2, 0).reshape(4, 3, 2, 2, 2)
    ref = at_mask(F.conv_transpose3d(xcd, w_t, stride=2), fmask)
    assert (out.feats - ref).abs().max() <= TOL
    r = torch.randn_like(ref)
    gx, gw = torch.autograd.grad((out.feats * r).sum(), [xs.feats, conv.weight])
    gxd, gwd = torch.autograd.grad((ref * r).sum(), [xcd, conv.weight])
    cmask_dense = to_dense(xs.replace(torch.ones(len(xs), 1)), offset=(2, -4, 0), shape=(5, 5, 5), batch_size=2)[0][:, 0] > 0
    assert (gx - at_mask(gxd, cmask_dense)).abs().max() <= TOL
    assert (gw - gwd).abs().max() <= TOL * max(1.0, gwd.abs().max())


def test_gradcheck_float64():
    xd, mask = random_grid(41, d=4, c=2, density=0.5, dtype=torch.float64)
    xs = from_dense(xd, mask, offset=(0, 0, 0))
    x = xs.feats.clone().requires_grad_(True)
    for k in (3, 5):
        w = torch.randn(k**3, 2, 3, dtype=torch.float64, requires_grad=True)
        table = xs.cset.neighbour_map(k)
        assert torch.autograd.gradcheck(lambda a, b: ops._SubmConvFn.apply(a, b, table), (x, w))
    coarse = xs.cset.downsample(2)
    flat, child = xs.cset.transfer_maps(coarse)
    w = torch.randn(8, 2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ops._DownConvFn.apply(a, b, child, flat), (x, w))
    xc = torch.randn(len(coarse), 3, dtype=torch.float64, requires_grad=True)
    w2 = torch.randn(8, 3, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ops._UpConvFn.apply(a, b, child, flat), (xc, w2))
    pts = (torch.rand(7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f, p: sample_at(xs.replace(f), p), (x, pts))


# ---------------------------------------------------------------------- pointwise layers
def test_batchnorm_and_activations_match_dense_on_active_sites():
    xd, mask = random_grid(51, d=7, c=4, batch=2)
    xs = from_dense(xd, mask)
    bn = SparseBatchNorm(4)
    ref_bn = torch.nn.BatchNorm1d(4)
    rows = at_mask(xd, mask)
    y = bn(xs).feats
    assert (y - ref_bn(rows)).abs().max() <= TOL
    # statistics use active sites only: normalised features have zero mean per channel
    assert y.mean(0).abs().max() <= 1e-5
    assert torch.allclose(bn.running_mean, ref_bn.running_mean)
    assert torch.equal(SparseReLU()(xs).feats, at_mask(F.relu(xd), mask))
    assert (SparseELU()(xs).feats - at_mask(F.elu(xd), mask)).abs().max() <= 1e-6


# ---------------------------------------------------------------------- set algebra and dense conversion
def test_union_intersection_cat_match_dense():
    ad, am = random_grid(61, d=6, c=2)
    bd, bm = random_grid(62, d=6, c=2)
    a, b = from_dense(ad, am, offset=(1, 1, 1)), from_dense(bd, bm, offset=(1, 1, 1))
    u = union(a, b)
    um = am | bm
    assert len(u) == int(um.sum())
    ud, off = to_dense(u, offset=(1, 1, 1), shape=(6, 6, 6))
    assert torch.allclose(ud, ad + bd, atol=1e-6)
    i = intersection(a, b)
    assert len(i) == int((am & bm).sum())
    idense, _ = to_dense(i, offset=(1, 1, 1), shape=(6, 6, 6))
    assert torch.allclose(idense, ad * (am & bm)[:, None])
    c = cat(a, b)
    cd, _ = to_dense(c, offset=(1, 1, 1), shape=(6, 6, 6))
    assert c.num_channels == 4 and len(c) == int(um.sum())
    assert torch.allclose(cd, torch.cat([ad, bd], 1))
    same = cat(a, a.replace(a.feats * 2))
    assert same.cset is a.cset and torch.allclose(same.feats[:, 2:], 2 * a.feats)
    # features_at: a's features at b's coordinates, zero where a has no voxel
    fa = a.features_at(b)
    assert torch.allclose(fa, at_mask(ad, bm))


def test_dense_roundtrip_and_gradients():
    xd, mask = random_grid(71, d=5, c=3, batch=3)
    xd = xd.requires_grad_(True)
    xs = from_dense(xd, mask, offset=(-2, -2, -2), stride=2)
    assert xs.stride == 2 and (xs.coords[:, 1:] % 2 == 0).all()
    back, off = to_dense(xs, offset=(-2, -2, -2), shape=(5, 5, 5))
    assert off.tolist() == [-2, -2, -2]
    assert torch.equal(back, xd)
    back.sum().backward()
    assert torch.equal(xd.grad, mask[:, None].expand_as(xd).float())


def test_world_points_convention():
    cs = torch.tensor([[0, 2, 4, -2]])
    t1 = SparseTensor(cs, torch.ones(1, 1), 1, 0.5, (10.0, 0.0, -1.0))
    assert t1.world_points().tolist() == [[11.0, 2.0, -2.0]]
    t2 = SparseTensor(cs, torch.ones(1, 1), 2, 0.5, (10.0, 0.0, -1.0))
    assert t2.world_points().tolist() == [[11.25, 2.25, -1.75]]  # centre of fine voxels c, c+1


@pytest.mark.parametrize("stride", [1, 2])
def test_sample_at_matches_grid_sample(stride):
    xd, mask = random_grid(81, d=7, c=3, density=0.6)
    vs, origin, offset = 0.5, (3.0, -2.0, 1.0), (-4, 2, 6)
    xs = from_dense(xd, mask, offset=offset, stride=stride, voxel_size=vs, origin=origin)
    g = torch.Generator().manual_seed(4)
    lat = torch.rand(200, 3, generator=g) * 8 - 1  # lattice coordinates, some outside the grid
    centre0 = torch.tensor(origin) + (torch.tensor(offset) + (stride - 1) / 2) * vs
    pts = centre0 + lat * stride * vs
    got = sample_at(xs, pts)
    grid = (2 * lat / 6 - 1).flip(-1).view(1, 1, 1, -1, 3)  # grid_sample wants (z, y, x) → (W, H, D)
    ref = F.grid_sample(xd, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0, :, 0, 0].T
    assert (got - ref).abs().max() <= TOL
    nearest = sample_at(xs, pts, mode="nearest")
    ref_n = F.grid_sample(xd, grid, mode="nearest", padding_mode="zeros", align_corners=True)[0, :, 0, 0].T
    assert (nearest - ref_n).abs().max() <= TOL
    # renormalised weights reproduce a constant field wherever any corner is present
    ones = xs.replace(torch.ones(len(xs), 1))
    r = sample_at(ones, pts, renormalize=True)
    anyc = sample_at(ones, pts) > 0
    assert torch.allclose(r[anyc], torch.ones_like(r[anyc]))


def test_from_voxels_batches_sparse_voxels():
    import numpy as np

    from stages.core.voxels import SparseVoxels

    a = SparseVoxels(np.array([[0, 0, 0], [1, 0, 0]]), 0.5, (1, 2, 3), {"occupancy": np.array([1, 0], np.uint8)})
    b = SparseVoxels(np.array([[5, 5, 5]]), 0.5, (1, 2, 3), {"occupancy": np.array([1], np.uint8)})
    t = SparseTensor.from_voxels([a, b], ["occupancy"])
    assert t.coords.tolist() == [[0, 0, 0, 0], [0, 1, 0, 0], [1, 5, 5, 5]]
    assert t.feats[:, 0].tolist() == [1.0, 0.0, 1.0]
    assert np.allclose(t.world_points().numpy(), np.concatenate([a.world_points(), b.world_points()]))


# ---------------------------------------------------------------------- U-Net
def tube_voxels(seed=0, n_tubes=3, length=30, radius=2.0):
    """Small vessel-like tube set (N×4 coords, batch 0)."""
    g = torch.Generator().manual_seed(seed)
    pts = []
    for _ in range(n_tubes):
        p0 = torch.rand(3, generator=g) * 20
        d = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0)
        t = torch.linspace(0, length, length * 2)[:, None]
        centre = p0 + t * d
        r = torch.arange(-3, 4)
        cube = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3).float()
        cube = cube[cube.norm(dim=1) <= radius]
        pts.append((centre[:, None] + cube[None]).reshape(-1, 3).round().long())
    c = torch.unique(torch.cat(pts), dim=0)
    return torch.cat([torch.zeros(len(c), 1, dtype=torch.long), c], 1)


def test_unet_forward_backward_and_shared_maps():
    coords = tube_voxels()
    g = torch.Generator().manual_seed(0)
    x = SparseTensor(coords, torch.randn(len(coords), 5, generator=g), voxel_size=0.5)
    torch.manual_seed(0)
    net = SparseUNet(5, 2, widths=(8, 12, 16), blocks=(1, 1, 1))
    out = net(x)
    assert out.feats.shape == (len(coords), 2) and out.cset is x.cset
    out.feats.square().mean().backward()
    grads = [p.grad for p in net.parameters()]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in grads)
    assert sum(float(gr.abs().sum()) for gr in grads) > 0
    # one neighbour table per level, shared by every layer on it; encoder sets reused by the decoder
    assert set(k for k in x.cset._cache if k[0] == "subm") == {("subm", 3)}
    c1 = x.cset.downsample(2)
    assert c1.parent is x.cset and ("subm", 3) in c1._cache
    # deterministic given the seed
    torch.manual_seed(0)
    net2 = SparseUNet(5, 2, widths=(8, 12, 16), blocks=(1, 1, 1))
    assert torch.equal(net2(x).feats, out.feats)


def test_unet_learns_a_sparse_mapping():
    # a couple of dozen steps must fit a simple target (occupancy of the voxel's upper half-space)
    coords = tube_voxels(seed=1, n_tubes=1, length=15)
    feats = torch.randn(len(coords), 3, generator=torch.Generator().manual_seed(1))
    target = (coords[:, 3] > coords[:, 3].float().median()).long()
    x = SparseTensor(coords, feats)
    torch.manual_seed(1)
    net = SparseUNet(3, 2, widths=(8, 16), blocks=(1, 1))
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    losses = []
    for _ in range(25):
        loss = F.cross_entropy(net(x).feats, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    coords = tube_voxels(seed=2)
    feats = torch.randn(len(coords), 4, generator=torch.Generator().manual_seed(2))
    torch.manual_seed(0)
    net = SparseUNet(4, 2, widths=(8, 16, 24), blocks=(1, 1, 1))
    x = SparseTensor(coords, feats)
    out = net(x)
    out.feats.sum().backward()
    g_cpu = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    net_c = net.cuda()
    xc = x.to("cuda")
    out_c = net_c(xc)
    assert out_c.feats.is_cuda and out_c.cset.device.type == "cuda"
    out_c.feats.sum().backward()
    assert (out_c.feats.cpu() - out.feats).abs().max() <= 1e-3
    for a, b in zip(g_cpu, net_c.parameters()):
        assert (a - b.grad.cpu()).abs().max() <= 1e-3 * max(1.0, float(a.abs().max()))
    pts = x.world_points()[:50].float().cuda() + 0.3
    assert torch.allclose(sample_at(xc, pts).cpu(), sample_at(x, pts.cpu()), atol=1e-5)


def test_inplace_batchnorm_matches_batch_norm_without_gradients():
    xd, mask = random_grid(52, d=7, c=4, batch=2)
    xs = from_dense(xd, mask)
    bn = SparseBatchNorm(4, track_running_stats=False, inplace=True)
    with torch.no_grad():
        bn.weight.uniform_(0.5, 2.0)
        bn.bias.uniform_(-1.0, 1.0)
    ref = torch.nn.functional.batch_norm(xs.feats, None, None, bn.weight, bn.bias, True, 0.0, bn.eps)
    with torch.no_grad():
        feats = xs.feats.clone()
        out = bn(xs.replace(feats)).feats
    assert out.data_ptr() == feats.data_ptr()  # normalised in place
    assert (out - ref).abs().max() <= 1e-5
    with torch.no_grad():  # layers that keep running statistics never take the in-place path
        tracked = SparseBatchNorm(4, inplace=True)
        feats = xs.feats.clone()
        assert tracked(xs.replace(feats)).feats.data_ptr() != feats.data_ptr()


def test_conv_of_parts_equals_conv_of_concatenation():
    xd, mask = random_grid(53, d=8, c=5, batch=1)
    a = from_dense(xd, mask)
    b = a.replace(torch.randn(len(a), 3, generator=torch.Generator().manual_seed(1)))
    conv = SubmConv3d(8, 6, 3, bias=True)
    ref = conv(cat(a, b)).feats
    assert (conv((a, b)).feats - ref).abs().max() <= 1e-5
    with torch.no_grad():
        assert (conv((a, b)).feats - ref).abs().max() <= 1e-5
    with pytest.raises(ValueError, match="channels"):
        conv((a, a))


def test_unet_inference_path_matches_the_gradient_path():
    """Under no_grad the U-Net normalises and adds in place and never concatenates decoder inputs;
    its output must equal the ordinary (autograd) computation."""
    xd, mask = random_grid(54, d=12, c=5, batch=1)
    x = from_dense(xd, mask)
    net = SparseUNet(5, 2, widths=(8, 12, 16), blocks=(1, 1, 1))
    for m in net.modules():
        if isinstance(m, SparseBatchNorm):
            m.track_running_stats = False
            m.running_mean = m.running_var = m.num_batches_tracked = None
    ref = net(x).feats.detach()
    with torch.no_grad():
        out = net(x).feats
    assert (out - ref).abs().max() <= 1e-4

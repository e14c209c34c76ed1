"""Segmenter-style mask corruption (stages.render.mask_noise) and its use in SBP training pairs."""

import numpy as np
import pytest
from scipy import ndimage

from stages.render.mask_noise import MaskNoise, corrupt_mask

NONE = MaskNoise(breaks=0, spurs=0, blobs=0, widened=0, boundary_p=0)


def _vessel(size=256, width=7):
    """One straight horizontal vessel across the image."""
    m = np.zeros((size, size), bool)
    m[size // 2 - width // 2: size // 2 + width // 2 + 1, 20:size - 20] = True
    return m


def _components(m):
    return ndimage.label(m)[1]


def test_same_seed_same_corruption_and_seeds_differ():
    m = _vessel()
    a = corrupt_mask(m, np.random.default_rng(5))
    b = corrupt_mask(m, np.random.default_rng(5))
    c = corrupt_mask(m, np.random.default_rng(6))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a, m) and m.sum() == _vessel().sum()  # input untouched


def test_no_error_kinds_leaves_the_mask_as_it_is():
    m = _vessel()
    assert np.array_equal(corrupt_mask(m, np.random.default_rng(0), NONE), m)
    empty = np.zeros((64, 64), bool)
    assert not corrupt_mask(empty, np.random.default_rng(0)).any()


def test_breaks_cut_the_vessel():
    m = _vessel()
    out = corrupt_mask(m, np.random.default_rng(1), MaskNoise(**{**NONE.__dict__, "breaks": 4.0}))
    assert not (out & ~m).any()  # only removes
    # a break is at least as wide as the vessel, so each one inside the vessel splits it
    assert _components(out) >= 2
    assert m.sum() - out.sum() >= 7 * 3


def test_spurs_and_blobs_only_add():
    m = _vessel()
    for kind in ("spurs", "blobs"):
        out = corrupt_mask(m, np.random.default_rng(2), MaskNoise(**{**NONE.__dict__, kind: 5.0}))
        assert (out & m).sum() == m.sum(), kind
        assert (out & ~m).sum() > 20, kind


def test_widening_stays_near_the_vessel_and_boundary_bias_moves_the_border():
    m = _vessel()
    widened = corrupt_mask(m, np.random.default_rng(3), MaskNoise(**{**NONE.__dict__, "widened": 3.0}))
    added = widened & ~m
    assert added.sum() > 0
    assert ndimage.distance_transform_edt(~m)[added].max() <= 3.0 + 1e-9  # at most widen_by_px[1] px off
    sizes = set()
    for seed in range(6):
        out = corrupt_mask(m, np.random.default_rng(seed), MaskNoise(**{**NONE.__dict__, "boundary_p": 1.0}))
        sizes.add(int(out.sum()))
    # one-pixel erosion and dilation of a 7-px-wide bar: both happen over six draws
    assert min(sizes) < m.sum() < max(sizes)


def test_lengths_scale_with_the_image_size():
    small = corrupt_mask(_vessel(128, 3), np.random.default_rng(4), MaskNoise(**{**NONE.__dict__, "spurs": 6.0}))
    large = corrupt_mask(_vessel(512, 13), np.random.default_rng(4), MaskNoise(**{**NONE.__dict__, "spurs": 6.0}))
    added_small = (small & ~_vessel(128, 3)).sum()
    added_large = (large & ~_vessel(512, 13)).sum()
    assert added_large / max(added_small, 1) == pytest.approx(16, rel=0.5)  # area: (512/128)² times


def test_training_pairs_with_mask_noise_keep_the_pair_and_its_truth():
    from stages.sbp import train as T
    from stages.poses import PoseModel
    from stages.render.phantom import tube_case
    from stages.sbp import SBPConfig

    case = tube_case(seed=1)
    poses = PoseModel.default(seed=0)
    model_cfg = SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 16), unet_blocks=(1, 1))
    clean_cfg = T.TrainConfig(size=128, misalign_3d=0.0)
    noisy_cfg = T.TrainConfig(size=128, misalign_3d=0.0, mask_noise=1.0)
    runs = {}
    for name, cfg in (("clean", clean_cfg), ("noisy", noisy_cfg)):
        _, truth, sample = T.make_example(case, poses, np.random.default_rng(9), cfg, model_cfg,
                                          noise_rng=np.random.default_rng(10))
        runs[name] = (truth, sample)
    (t0, s0), (t1, s1) = runs["clean"], runs["noisy"]
    # same poses, placement and truth: the noise has its own random stream
    assert np.allclose(s0["camera_a"].R, s1["camera_a"].R) and np.allclose(s0["camera_b"].K, s1["camera_b"].K) and np.allclose(t0.origin, t1.origin)
    assert np.array_equal(t0.coords, t1.coords)
    assert not np.array_equal(s0["mask_a"], s1["mask_a"]) or not np.array_equal(s0["mask_b"], s1["mask_b"])

"""The 2D segmenter's masks of training pairs (stages.render.segmenter_masks, ``--unet-masks``)."""

import numpy as np
import pytest

from stages.segment.scores import dice_2d


@pytest.fixture(scope="module")
def pair():
    from stages.sbp import train as T
    from stages.poses import PoseModel
    from stages.render.phantom import tube_case
    from stages.sbp import SBPConfig

    case = tube_case(seed=1)
    poses = PoseModel.default(seed=0)
    model_cfg = SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 16), unet_blocks=(1, 1))
    out = {}
    # a large warp of view b, so a mask that ignored it would visibly miss the silhouette
    for name, share in (("silhouette", 0.0), ("unet", 1.0)):
        cfg = T.TrainConfig(size=256, misalign_3d=0.0, misalign_px=6.0, unet_masks=share)
        _, truth, sample = T.make_example(case, poses, np.random.default_rng(9), cfg, model_cfg,
                                          noise_rng=np.random.default_rng(10))
        out[name] = (truth, sample)
    return case, out


def test_unet_masks_keep_the_pair_and_its_truth_and_follow_its_geometry(pair):
    from stages.render.raster import rasterise_mask

    case, runs = pair
    (t0, s0), (t1, s1) = runs["silhouette"], runs["unet"]
    assert np.array_equal(t0.coords, t1.coords) and np.allclose(t0.origin, t1.origin)
    assert np.allclose(s0["camera_b"].K, s1["camera_b"].K)
    for view in ("a", "b"):
        m0, m1 = s0[f"mask_{view}"], s1[f"mask_{view}"]
        assert m1.dtype == bool and m1.shape == m0.shape
        assert not np.array_equal(m0, m1)  # the segmenter's mask, not the silhouette
        assert dice_2d(m1, m0) > 0.7, view  # but of the same vessels
    # view b's frame shows the warped lumen: its mask agrees with the warped silhouette better than
    # with the unwarped one
    unwarped = rasterise_mask(s1["vertices_b"], case.faces, s1["camera_b"])
    assert dice_2d(s1["mask_b"], s0["mask_b"]) > dice_2d(s1["mask_b"], unwarped) + 0.05


def test_unet_masks_are_a_pure_function_of_the_seed(pair):
    from stages.render.segmenter_masks import segmenter_masks

    case, runs = pair
    sample = runs["silhouette"][1]
    a = segmenter_masks(sample, case, np.random.default_rng(3))
    b = segmenter_masks(sample, case, np.random.default_rng(3))
    c = segmenter_masks(sample, case, np.random.default_rng(4))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert any(not np.array_equal(x, y) for x, y in zip(a, c))

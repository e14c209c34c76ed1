"""The 2D vessel segmenter: model shapes, augmentation, inference + baselines, artefact, run loading, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.core.errors import UserError


def _tube_image(H=256, W=256, seed=0):
    """A dark curved tube (width ~7 px) on a noisy grey background with dark rounded collimator corners."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:H, 0:W]
    centre_c = W / 2 + 40 * np.sin(rr / H * np.pi * 1.3)
    d = np.abs(cc - centre_c)
    truth = (d <= 3.5) & (rr > 20) & (rr < H - 20)
    img = 110 + 8 * np.sin(cc / 37.0) + rng.normal(0, 3, (H, W))
    img = img - 55 * np.clip(3.5 + 0.5 - d, 0, 1) * ((rr > 20) & (rr < H - 20))
    # collimator: dark outside a rounded rectangle
    y, x = (rr - (H - 1) / 2) / W, (cc - (W - 1) / 2) / W
    inside = (np.abs(y) < 0.47) & (np.abs(x) < 0.47) & (np.hypot(y, x) < 0.6)
    img = np.where(inside, img, 8 + rng.normal(0, 2, (H, W)))
    return np.clip(img, 0, 255).astype(np.float32), truth, inside


def _dice(a, b):
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    return 2 * (a & b).sum() / max(a.sum() + b.sum(), 1)


def test_model_any_size_and_small():
    import torch

    from stages.segment.model import UNet2D

    m = UNet2D().eval()
    n = sum(p.numel() for p in m.parameters())
    assert 50_000 < n < 1_000_000
    with torch.no_grad():
        y = m(torch.randn(2, 1, 100, 131))
    assert y.shape == (2, 1, 100, 131)


def test_shipped_weights_small_and_loadable():
    from stages.segment import load_model
    from stages.segment.train import DEFAULT_WEIGHTS

    assert DEFAULT_WEIGHTS.exists(), "stages/weights/seg.pt must ship with the package"
    assert DEFAULT_WEIGHTS.stat().st_size <= 5 * 1024 * 1024
    model, thr, info = load_model()
    assert 0 < thr < 1 and info.get("steps", 0) > 0


def test_normalise_frame_is_affine_invariant():
    from stages.segment.model import normalise_batch, normalise_frame

    img, _, _ = _tube_image()
    a = normalise_frame(img)
    b = normalise_frame(3.7 * img + 500)  # another bit depth / window
    np.testing.assert_allclose(a, b, atol=1e-4)
    import torch

    c = normalise_batch(torch.from_numpy(img)[None, None])[0, 0].numpy()
    assert np.abs(c - a).max() < 0.05  # same formula up to quantile interpolation


def test_augment_batch_deterministic_and_consistent():
    import torch

    from stages.segment.augment import augment_batch

    img, truth, _ = _tube_image(256, 256)
    x = torch.from_numpy(np.stack([img] * 4))[:, None]
    y = torch.from_numpy(np.stack([truth] * 4).astype(np.float32))[:, None]
    a1, m1 = augment_batch(x, y, torch.Generator().manual_seed(3), crop=128)
    a2, m2 = augment_batch(x, y, torch.Generator().manual_seed(3), crop=128)
    assert a1.shape == (4, 1, 128, 128) and m1.shape == (4, 1, 128, 128)
    assert torch.equal(a1, a2) and torch.equal(m1, m2)
    assert set(torch.unique(m1).tolist()) <= {0.0, 1.0}
    assert torch.isfinite(a1).all()
    a3, _ = augment_batch(x, y, torch.Generator().manual_seed(4), crop=128)
    assert not torch.equal(a1, a3)


def test_unet_segments_a_tube_and_not_the_collimator():
    from stages.segment import segment_frames

    img, truth, inside = _tube_image(256, 256)
    prob, mask = segment_frames(img, method="unet")
    assert prob.shape == img.shape and mask.dtype == np.uint8
    assert _dice(mask, truth) > 0.7
    assert mask[~inside].sum() == 0  # the dark collimator region and its edge are not vessel


def test_field_of_view_keeps_thick_dark_vessel_at_the_edge():
    """A thick, black (saturated) vessel running out of the open field is as dark as the collimator
    blades; the field of view must keep it (convex hull) and still leave the dark corners out."""
    from stages.segment.infer import field_of_view

    img, _, inside = _tube_image(256, 256)
    rr, cc = np.mgrid[0:256, 0:256]
    band = (np.abs(rr - 128) <= 10) & (cc > 150) & inside  # 21 px wide, black, up to the right blade
    img = np.where(band, 0.0, img).astype(np.float32)
    fov = field_of_view(img[None])
    assert fov[band & (cc < 230)].all()  # kept up to a margin from the blade
    assert not fov[~inside].any()  # blades and corners stay outside


@pytest.mark.parametrize("method", ["vesselness", "threshold"])
def test_baselines_find_the_tube(method):
    from stages.segment import segment_frames

    img, truth, inside = _tube_image(256, 256)
    prob, mask = segment_frames(img[None], method=method)
    assert mask.shape == (1, 256, 256)
    assert _dice(mask[0], truth) > 0.5
    assert mask[0][~inside].sum() == 0


def test_segment_frames_rejects_bad_input():
    from stages.segment import segment_frames

    with pytest.raises(UserError):
        segment_frames(np.zeros((3, 8, 8)), method="unet")
    with pytest.raises(UserError, match="unknown method"):
        segment_frames(np.zeros((64, 64)), method="magic")


def _write_stack(tmp_path, T=3, geometry=True):
    img, truth, _ = _tube_image(128, 128)
    stack = np.stack([img] * T)
    p = tmp_path / "run.npy"
    np.save(p, stack)
    if geometry:
        (tmp_path / "run.json").write_text(json.dumps({"alpha": 30, "beta": 0, "sid": 1000, "sod": 750,
                                                        "spacing": 0.3, "frame_time_ms": 50}))
    return p, truth


def test_load_run_variants(tmp_path):
    from PIL import Image

    from stages.core.runs import load_run

    p, _ = _write_stack(tmp_path)
    r = load_run(p)
    assert r.frames.shape == (3, 128, 128) and r.camera is not None
    np.testing.assert_allclose(r.frame_times_ms, [0, 50, 100])
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(np.full((40, 50), 100 + i, np.uint8)).save(folder / f"f{i:02d}.png")
    r2 = load_run(folder)
    assert r2.frames.shape == (2, 40, 50) and r2.camera is None and r2.frames[1, 0, 0] == 101
    Image.fromarray(np.zeros((41, 50), np.uint8)).save(folder / "f99.png")
    with pytest.raises(UserError, match="differ in size"):
        load_run(folder)
    with pytest.raises(UserError, match="no such file"):
        load_run(tmp_path / "missing.dcm")
    (tmp_path / "bad.json").write_text(json.dumps({"alpha": 1}))
    np.save(tmp_path / "bad.npy", np.zeros((2, 32, 32)))
    with pytest.raises(UserError, match="lacks"):
        load_run(tmp_path / "bad.npy")


def test_masks_artefact_roundtrip(tmp_path):
    from stages.segment import read_masks, segment_run, write_masks

    p, truth = _write_stack(tmp_path)
    res = segment_run(p, method="unet")
    out = write_masks(tmp_path / "m.zarr", res)
    m = read_masks(out)
    assert m["prob"].shape == (3, 128, 128) and m["mask"].dtype == np.uint8
    assert m["attrs"]["kind"] == "autocar.vessel-masks"
    assert m["attrs"]["method"] == "unet" and m["attrs"]["threshold"] == pytest.approx(0.5)
    assert m["attrs"]["camera"]["rows"] == 128
    assert m["attrs"]["frame_times_ms"] == [0.0, 50.0, 100.0]
    np.testing.assert_array_equal(m["mask"], res["mask"])
    assert np.abs(m["prob"] - res["prob"]).max() < 1e-3  # float16
    # stored with exactly NumPy's rounding (torch casts it, 50× faster for values below float16's normal range)
    np.testing.assert_array_equal(m["prob"], res["prob"].astype(np.float16).astype(np.float32))


def test_cli_segment(tmp_path, cli):
    p, truth = _write_stack(tmp_path, T=2)
    out = tmp_path / "masks.zarr"
    r = cli("segment", p, "-o", out)
    assert r.exit_code == 0, r.output
    assert out.exists() and (tmp_path / "masks.gif").exists() and (tmp_path / "masks_f000.png").exists()
    r = cli("segment", tmp_path / "nope.dcm", "-o", out)
    assert r.exit_code == 2 and "nope.dcm" in r.output


def test_render_training_frames(tmp_path):
    from stages.render.phantom import tube_case
    from stages.segment.data import render_case_frames

    case = tube_case(5)
    path = case.save(tmp_path / "case_0005_left.zarr", stage="test")
    fr, mk, sp = render_case_frames(path, seed=1, n_scenes=1, frames_per_scene=2, size=128)
    assert fr.shape == (2, 128, 128) and fr.dtype == np.uint8 and mk.shape == fr.shape
    assert np.all(sp > 0)
    # a labelled pixel is darker than the frame's median when the vessel is filled
    for f, m in zip(fr, mk):
        if m.sum() > 20:
            assert np.median(f[m > 0]) < np.median(f)


def test_truth_is_contrast_and_open_field():
    """The segmentation truth: iodine path ≥ 0.3 mm and inside the collimator's open field, nothing else."""
    from stages.segment.data import VISIBLE_MM, visible_vessel

    L = np.array([[0.0, VISIBLE_MM - 0.01, VISIBLE_MM, 2.0], [2.0, 2.0, 2.0, 0.0]])
    open_field = np.array([[1, 1, 1, 1], [0, 1, 1, 1]], bool)
    np.testing.assert_array_equal(visible_vessel(L, open_field), [[0, 0, 1, 1], [0, 1, 1, 0]])


def test_sampling_weights_favour_partial_frames():
    from stages.segment.train import sampling_weights

    masks = np.zeros((8, 4, 4), np.uint8)  # two scenes of 4 frames; vessel areas 10/10/5/0 and 4/4/4/3
    for i, a in enumerate([10, 10, 5, 0, 4, 4, 4, 3]):
        masks[i].flat[:a] = 1
    p = sampling_weights(masks, 4, 3.0)
    assert p.sum() == pytest.approx(1.0)
    # partial: frame 2 (5 < 0.8·10) and frame 7 (3 < 0.8·4); empty and filled frames weigh 1
    np.testing.assert_allclose(p * 12, [1, 1, 3, 1, 1, 1, 1, 3])
    np.testing.assert_allclose(sampling_weights(masks, 4, 1.0), np.full(8, 1 / 8))


def test_fine_tune_from_weights(tmp_path):
    """``init`` starts from shipped-format weights and keeps their training record; ``steps`` bounds the run."""
    import torch

    from stages.core.artefacts import save_npz
    from stages.segment.data import KIND, SCHEMA
    from stages.segment.model import UNet2D
    from stages.segment.train import export_weights, train

    img, truth, _ = _tube_image(128, 128)
    (tmp_path / "seg" / "train").mkdir(parents=True)
    save_npz(tmp_path / "seg" / "train" / "case_0000_left.npz",
             {"frames": np.stack([img] * 4).astype(np.uint8), "masks": np.stack([truth] * 4).astype(np.uint8),
              "spacing": np.full(4, 0.3, np.float32)}, kind=KIND, schema_version=SCHEMA, stage="test")
    torch.manual_seed(0)
    base = export_weights(UNet2D(), tmp_path / "base.pt", info={"steps": 7})
    info = train(data=tmp_path / "seg", ckpt=tmp_path / "ckpt.pt", weights=tmp_path / "ft.pt", steps=2, batch=2,
                 crop=64, init=base, partial_weight=3.0)
    assert info["steps"] == 2 and info["init"] == {"steps": 7} and info["partial_weight"] == 3.0
    ft = torch.load(tmp_path / "ft.pt", weights_only=False)
    assert ft["train"]["init"]["steps"] == 7 and (tmp_path / "ckpt.pt").exists()


def test_phantom_collimator_not_vessel(phantom_dir):
    """Real GE phantom frames: masks stay inside the field of view, nothing in the dark corners."""
    from scipy import ndimage

    from stages.core.dicom_io import read_xa
    from stages.segment import segment_frames

    run = read_xa(phantom_dir / "IM8.dcm")
    frames = run.frames[-2:]
    prob, mask = segment_frames(frames, method="unet")
    sm = ndimage.gaussian_filter(np.median(frames, 0), 6)
    dark = sm < 0.5 * np.median(sm)
    lab, _ = ndimage.label(dark)  # collimator corners / shutters: the dark parts touching the image border
    edge_labels = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    dark = np.isin(lab, edge_labels[edge_labels > 0])
    assert dark.sum() > 1000
    border = ndimage.binary_dilation(dark, iterations=3)  # the FOV keeps a 4-px margin
    assert mask[:, border].sum() == 0
    frac = mask.mean()
    assert 0.01 < frac < 0.15


@pytest.mark.parametrize("frames", [1, 2, 7, 42])
def test_temporal_median_equals_numpy_median(frames):
    from stages.segment.vesselness import temporal_median

    stack = np.random.default_rng(frames).normal(size=(frames, 33, 17)).astype(np.float32)
    assert np.array_equal(temporal_median(stack), np.median(stack, axis=0))


def test_batchnorm_folding_keeps_the_segmenter_output():
    torch = pytest.importorskip("torch")
    from stages.segment.model import UNet2D, fold_batchnorm

    torch.manual_seed(0)
    model = UNet2D()
    for m in model.modules():  # trained-looking statistics, so the folding has something to fold
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    model.eval()
    folded = fold_batchnorm(model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())  # the original is untouched
    x = torch.randn(2, 1, 70, 90)
    with torch.inference_mode():
        assert torch.allclose(model(x), folded(x), atol=1e-4)

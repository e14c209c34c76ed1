"""SBP network: candidates, target alignment, loss, gradients into the 2D encoder, bad input, training."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.sbp import SBPConfig, SBPNet, prepare_pair
from stages.sbp.loss import align_targets, sbp_loss, skeleton_labels, skeleton_recall_loss, soft_dice_loss
from stages.core.voxels import SparseVoxels

TINY = SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 16), unet_blocks=(1, 1))


@pytest.fixture(scope="module")
def tube():
    from stages.render.phantom import tube_case

    return tube_case(seed=3)


def _render(case, cams, t=np.zeros(3)):
    from stages.render.raster import rasterise_mask

    return [rasterise_mask(case.vertices.astype(float) + t, case.faces, c) for c in cams]


def _cams(size=256):
    return (Camera.from_carm(30, 20, 1000, 750, 0.3 * 512 / size, size, size),
            Camera.from_carm(-30, -20, 1000, 750, 0.3 * 512 / size, size, size))


def test_candidates_cover_the_ground_truth_lumen(tube):
    cams = _cams()
    lumen = tube.labels.world_points()[tube.labels.features["occupancy"] > 0]
    t = np.array([0.3, -1.1, 2.2]) - lumen.mean(0)  # whole tree in both fields of view, off-lattice shift
    masks = _render(tube, cams, t)
    truth = SparseVoxels(tube.labels.coords, tube.labels.voxel_size, tube.labels.origin + t, tube.labels.features)
    pair = prepare_pair(masks[0], masks[1], cams[0], cams[1], TINY, grid_offset_mm=truth.origin)
    targets = align_targets(pair.candidates, truth)
    # exact silhouettes: every lumen voxel is a candidate, and the lattices coincide
    assert targets["candidate_recall"] > 0.995
    assert targets["occupancy"].sum() == pytest.approx(truth.features["occupancy"].sum(), rel=0.01)
    # sparsity: the candidates are a small fraction of the dense box they span
    lo, hi = pair.candidates.bounds()
    assert len(pair.candidates) < 0.1 * np.prod(hi - lo + 1)


def test_align_targets_by_hand():
    cand = SparseVoxels(np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]]), 0.5, [0.0, 0.0, 0.0])
    # truth on the same lattice, origin one voxel further along x
    truth = SparseVoxels(np.array([[0, 0, 0], [3, 3, 3], [9, 9, 9]]), 0.5, [0.5, 0.0, 0.0],
                         {"occupancy": np.array([1, 1, 0], np.uint8), "centreness": np.array([0.8, 0.5, 0.0], np.float32)})
    t = align_targets(cand, truth)
    np.testing.assert_allclose(t["occupancy"], [0, 1, 0])  # truth voxel (0,0,0) sits at candidate (1,0,0)
    np.testing.assert_allclose(t["centreness"], [0, 0.8, 0])
    assert t["missed_occupancy"] == 1.0 and t["candidate_recall"] == 0.5
    assert "skeleton" not in t
    ts = align_targets(cand, SparseVoxels(truth.coords, 0.5, truth.origin, {**truth.features, "skeleton": np.array([1, 1, 0], bool)}))
    np.testing.assert_allclose(ts["skeleton"], [0, 1, 0])
    assert ts["missed_skeleton"] == 1.0  # truth voxel (3,3,3) is no candidate
    with pytest.raises(ValueError, match="not aligned"):
        align_targets(cand, SparseVoxels(truth.coords, 0.5, [0.2, 0, 0], truth.features))


def test_loss_counts_misses_and_rewards_the_truth():
    target = {"occupancy": np.array([1, 1, 0, 0], np.float32), "centreness": np.array([1, 0.5, 0, 0], np.float32),
              "missed_occupancy": 0.0, "missed_centreness": 0.0, "candidate_recall": 1.0}
    good = torch.tensor([[9.0, 9.0], [9.0, 0.0], [-9.0, -9.0], [-9.0, -9.0]])
    bad = -good
    assert sbp_loss(good, target)[0] < 0.8 < sbp_loss(bad, target)[0]
    p = torch.tensor([1.0, 1.0])
    t = torch.tensor([1.0, 1.0])
    assert soft_dice_loss(p, t, 0.0, eps=0.0) == pytest.approx(0.0)
    assert soft_dice_loss(p, t, 2.0, eps=0.0) == pytest.approx(1 - 4 / 6)  # two missed voxels


def test_skeleton_labels_follow_the_centreline(tube):
    skel = skeleton_labels(tube.labels)
    occ = tube.labels.features["occupancy"] >= 0.5
    assert skel.any() and not skel[~occ].any()  # S(X) ⊆ X
    # a tube: a thin line of voxels, far fewer than the lumen, all near its axis (high centreness)
    assert skel.sum() < 0.2 * occ.sum()
    cen = tube.labels.features["centreness"]
    assert np.median(cen[skel]) > np.median(cen[occ]) + 0.2


def test_training_skeletons_are_per_tree(tube):
    """The two trees of a case share its case_id: each keeps its own skeleton (regression)."""
    import dataclasses

    from stages.sbp import train as T

    from stages.render.phantom import tube_case

    other = dataclasses.replace(tube_case(seed=5), case_id=tube.case_id, side="right" if tube.side == "left" else "left")
    T._SKELETONS.clear()
    for case in (tube, other, tube):
        truth = T.shifted_labels(case, np.zeros(3), with_skeleton=True)
        assert len(truth.features["skeleton"]) == len(case.labels)
        np.testing.assert_array_equal(truth.features["skeleton"], skeleton_labels(case.labels))
    assert "skeleton" not in T.shifted_labels(tube, np.zeros(3)).features


def test_skeleton_recall_counts_centreline_misses():
    skel = torch.tensor([1.0, 1.0, 0.0, 0.0])
    assert skeleton_recall_loss(torch.tensor([1.0, 1.0, 0.0, 0.0]), skel, 0.0, eps=0.0) == pytest.approx(0.0)
    assert skeleton_recall_loss(torch.tensor([1.0, 1.0, 1.0, 1.0]), skel, 0.0, eps=0.0) == pytest.approx(0.0)  # recall only
    assert skeleton_recall_loss(torch.tensor([1.0, 0.0, 0.0, 0.0]), skel, 2.0, eps=0.0) == pytest.approx(1 - 1 / 4)
    target = {"occupancy": np.array([1, 1, 0, 0], np.float32), "centreness": np.array([1, 0.5, 0, 0], np.float32),
              "missed_occupancy": 0.0, "missed_centreness": 0.0, "candidate_recall": 1.0,
              "skeleton": np.array([1, 0, 0, 0], np.float32), "missed_skeleton": 0.0}
    miss_centre = torch.tensor([[-9.0, 9.0], [9.0, 0.0], [-9.0, -9.0], [-9.0, -9.0]])
    plain, parts = sbp_loss(miss_centre, target)
    weighted, parts_w = sbp_loss(miss_centre, target, skeleton_weight=1.0)
    assert "skeleton_recall" not in parts and parts_w["skeleton_recall"] > 0.4
    assert float(weighted) == pytest.approx(float(plain) + parts_w["skeleton_recall"], rel=1e-5)


def test_gradients_reach_the_2d_encoder(tube):
    torch.manual_seed(0)
    cams = _cams(128)
    masks = _render(tube, cams)
    pair = prepare_pair(masks[0], masks[1], cams[0], cams[1], TINY, grid_offset_mm=tube.labels.origin)
    net = SBPNet(TINY)
    out = net(pair, side="left")
    assert out.feats.shape == (len(pair.candidates), 2)
    loss, _ = sbp_loss(out.feats, align_targets(pair.candidates, tube.labels))
    loss.backward()
    enc = [p.grad.abs().sum().item() for p in net.encoder.parameters() if p.grad is not None]
    assert len(enc) == len(list(net.encoder.parameters())) and min(enc) > 0
    pred = net.predict(pair)
    assert set(pred.features) == {"occupancy", "centreness"} and 0 <= pred.features["occupancy"].min() <= 1


def test_widening_keeps_what_the_network_computes(tube):
    """embed_weights: a wider network holding a narrow one's weights predicts exactly the same, and its
    extra channels still get gradients (so training can grow them)."""
    from stages.sbp.model import embed_weights

    torch.manual_seed(1)
    cams = _cams(128)
    masks = _render(tube, cams)
    narrow = SBPNet(SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 16, 16), unet_blocks=(1, 2, 1)))
    for m in narrow.modules():  # non-trivial norms, so a misplaced channel would show
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            torch.nn.init.uniform_(m.weight, 0.5, 1.5)
            torch.nn.init.uniform_(m.bias, -0.3, 0.3)
    # every concatenation's first part grows, so old skip channels must move
    wide_cfg = SBPConfig(encoder_widths=(6, 10, 12), unet_widths=(12, 16, 24), unet_blocks=(1, 2, 1))
    wide = embed_weights(SBPNet(wide_cfg), narrow)
    pair = prepare_pair(masks[0], masks[1], cams[0], cams[1], TINY, grid_offset_mm=tube.labels.origin)
    a, b = narrow(pair, side="right").feats, wide(pair, side="right").feats
    assert a.abs().max() > 0.1
    torch.testing.assert_close(b, a, atol=2e-5, rtol=1e-4)
    loss, _ = sbp_loss(b, align_targets(pair.candidates, tube.labels))
    loss.backward()
    grown = wide.unet.head.weight.grad[0, 8:]  # head weights from the U-Net's extra output channels
    assert grown.abs().max() > 0
    for bad in (SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 12, 16), unet_blocks=(1, 2, 1)),
                SBPConfig(encoder_widths=(4, 8, 8), unet_widths=(8, 16, 16), unet_blocks=(1, 1, 1))):
        with pytest.raises(ValueError, match="not a widening"):
            embed_weights(SBPNet(bad), narrow)


def test_bad_pairs():
    ca = Camera.from_carm(30, 0, 1000, 750, 0.3, 64, 64)
    near = Camera.from_carm(35, 3, 1000, 750, 0.3, 64, 64)
    m = np.zeros((64, 64), bool)
    m[30:34, 10:50] = True
    with pytest.raises(UserError, match="apart"):
        prepare_pair(m, m, ca, near, TINY)
    with pytest.raises(UserError, match="mask is 32×32 but its camera expects 64×64"):
        prepare_pair(m[:32, :32], m, ca, Camera.from_carm(-40, 0, 1000, 750, 0.3, 64, 64), TINY)
    empty = prepare_pair(np.zeros((64, 64), bool), m, ca, Camera.from_carm(-40, 0, 1000, 750, 0.3, 64, 64), TINY)
    assert len(empty.candidates) == 0  # documented: empty masks give an empty prediction
    assert len(SBPNet(TINY).predict(empty).features["occupancy"]) == 0


@pytest.fixture(scope="module")
def tube_cases(tmp_path_factory):
    from stages.render.phantom import tube_case

    folder = tmp_path_factory.mktemp("cases")
    for s in range(3):
        tube_case(seed=s).save(folder / f"case_{s}.zarr")
    return folder


def _train_args(cases, run, steps, extra=()):
    return [str(cases), str(run), "--steps", str(steps), "--size", "128", "--ckpt-every", "1", "--val-every", "0",
            "--threads", "1", "--misalign-3d", "0", *extra]


@pytest.mark.slow
def test_training_resume_is_exact(tube_cases, tmp_path, monkeypatch):
    from stages.sbp import train as T

    monkeypatch.setattr(T, "SBPConfig", SBPConfig)
    small = TINY.as_dict()
    cfg = T.TrainConfig(steps=3, size=128, ckpt_every=1, val_every=0, threads=1, misalign_3d=0.0, model=small)
    T.train(tube_cases, tmp_path / "full", cfg)
    cfg2 = T.TrainConfig(**{**cfg.__dict__, "steps": 2})
    T.train(tube_cases, tmp_path / "part", cfg2)
    T.train(tube_cases, tmp_path / "part", cfg, resume=True)
    a = torch.load(tmp_path / "full" / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=False)["model"]
    assert max((a[k].float() - b[k].float()).abs().max().item() for k in a) < 1e-5
    rows = (tmp_path / "part" / "log.csv").read_text().strip().splitlines()
    assert rows[0].startswith("step,loss") and len(rows) == 4
    model = T.load_weights(tmp_path / "full" / "model.pt")
    from_ckpt = T.load_weights(tmp_path / "full" / "checkpoint.pt")  # what `autocar train --init` starts from
    for (k, v), w in zip(model.state_dict().items(), from_ckpt.state_dict().values()):
        assert torch.allclose(v.float(), w.float(), atol=2e-3, rtol=1e-3), k  # model.pt is stored in float16


@pytest.mark.slow
def test_distributed_replicas_stay_identical(tube_cases, tmp_path):
    """Two gloo processes under torchrun for a few steps: parameters identical on both ranks."""
    cfg = json.dumps(TINY.as_dict())
    script = tmp_path / "ddp.py"
    script.write_text(
        "import json, sys\n"
        "from stages.sbp import train as T\n"
        f"cfg = T.TrainConfig(steps=2, size=128, ckpt_every=1, val_every=0, threads=1, misalign_3d=0.0, model=json.loads({cfg!r}))\n"
        "s = T.train(sys.argv[1], sys.argv[2], cfg)\n"
        "print('SUMMARY', json.dumps(s))\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29617",
                           str(script), str(tube_cases), str(tmp_path / "run")], capture_output=True, text=True, env=env,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summaries = [json.loads(l.split("SUMMARY ", 1)[1]) for l in proc.stdout.splitlines() if "SUMMARY" in l]
    assert len(summaries) == 2 and all(s["world_size"] == 2 and s["step"] == 2 for s in summaries)
    assert max(s["replica_max_abs_diff"] for s in summaries) == 0.0


@pytest.mark.slow
def test_rendering_workers_do_not_change_training(tube_cases, tmp_path):
    """Pairs rendered in worker processes are the same pairs, in the same order: identical weights."""
    from stages.sbp import train as T

    cfg = T.TrainConfig(steps=2, accum=2, size=128, ckpt_every=1, val_every=0, threads=1, misalign_3d=0.0,
                        model=TINY.as_dict(), device="cpu")
    T.train(tube_cases, tmp_path / "in_process", cfg)
    summary = T.train(tube_cases, tmp_path / "workers", T.TrainConfig(**{**cfg.__dict__, "workers": 2}))
    assert summary["workers"] == 2 and summary["device"] == "cpu" and summary["step"] == 2
    a = torch.load(tmp_path / "in_process" / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "workers" / "checkpoint.pt", weights_only=False)["model"]
    assert max((a[k].float() - b[k].float()).abs().max().item() for k in a) < 1e-6
    logs = [(tmp_path / r / "log.csv").read_text().splitlines() for r in ("in_process", "workers")]
    assert [l.split(",")[1:8] for l in logs[0]] == [l.split(",")[1:8] for l in logs[1]]  # same losses and voxels


@pytest.mark.slow
def test_train_cli_architecture_options(tube_cases, tmp_path, cli):
    """--encoder-widths/--unet-widths/--unet-blocks build the network asked for; --init/--resume keep
    the architecture of the weights they continue (--init may widen it), and contradicting it is a
    one-line error."""
    from stages.sbp.train import load_weights
    from tests.conftest import assert_one_line_error

    common = ["--steps", "1", "--size", "128", "--val-every", "0", "--threads", "1", "--misalign-3d", "0"]
    run = tmp_path / "wide"
    res = cli("train", tube_cases, "-o", run, *common, "--encoder-widths", "4,8,12", "--unet-widths", "8,12,16",
              "--unet-blocks", "1,2,1")
    assert res.exit_code == 0, res.output
    cfg = load_weights(run / "model.pt").config
    assert (cfg.encoder_widths, cfg.unet_widths, cfg.unet_blocks) == ((4, 8, 12), (8, 12, 16), (1, 2, 1))
    # continuing: the architecture comes from the weights, so no options are needed …
    res = cli("train", tube_cases, "-o", tmp_path / "more", *common, "--init", run / "model.pt", "--mask-noise", "1")
    assert res.exit_code == 0, res.output
    assert load_weights(tmp_path / "more" / "model.pt").config.unet_blocks == (1, 2, 1)
    meta = torch.load(tmp_path / "more" / "model.pt", weights_only=False)["meta"]
    assert meta["train"]["mask_noise"] == 1.0  # recorded with the weights (the model card's data line)
    # … and options that contradict them are refused before anything is written
    res = cli("train", tube_cases, "-o", tmp_path / "bad", *common, "--init", run / "model.pt",
              "--unet-widths", "8,8,16")
    assert_one_line_error(res, "model.pt", "unet-widths 8,12,16", "can only widen")
    assert not (tmp_path / "bad" / "checkpoint.pt").exists()
    # … except a wider network, which starts from them (test_widening_keeps_what_the_network_computes)
    res = cli("train", tube_cases, "-o", tmp_path / "wider", *common, "--init", run / "model.pt",
              "--unet-widths", "8,16,24")
    assert res.exit_code == 0, res.output
    assert load_weights(tmp_path / "wider" / "model.pt").config.unet_widths == (8, 16, 24)
    res = cli("train", tube_cases, "-o", run, *common, "--resume", "--encoder-widths", "16,32,48")
    assert_one_line_error(res, "checkpoint.pt", "encoder-widths 4,8,12")
    res = cli("train", tube_cases, "-o", tmp_path / "bad", *common, "--unet-widths", "8,16", "--unet-blocks", "1")
    assert_one_line_error(res, "--unet-blocks", "one block count per U-Net level")
    res = cli("train", tube_cases, "-o", tmp_path / "bad", *common, "--encoder-widths", "wide")
    assert_one_line_error(res, "--encoder-widths", "comma-separated integers")


def test_training_device_is_checked():
    from stages.sbp.train import resolve_device

    assert resolve_device("cpu").type == "cpu"
    with pytest.raises(UserError, match="must be auto, cpu or cuda"):
        resolve_device("gpu0")
    if not torch.cuda.is_available():
        assert resolve_device("auto").type == "cpu"
        with pytest.raises(UserError, match="no CUDA device"):
            resolve_device("cuda")


def test_coarse_views_are_brought_to_the_training_pixel_size():
    from stages.core.geometry import Camera
    from stages.sbp.model import to_training_scale

    coarse = Camera.from_carm(30.0, 20.0, 1000.0, 750.0, 0.8, 256, 256)  # 0.6 mm at the isocentre
    mask = np.zeros((256, 256), bool)
    mask[100:110, 50:200] = True
    up, cam = to_training_scale(mask, coarse, 0.4)
    assert up.shape == (512, 512) and cam.isocentre_spacing == pytest.approx(0.3)
    assert up.sum() == 4 * mask.sum()  # a 2× finer copy of the same silhouette
    fine = Camera.from_carm(30.0, 20.0, 1000.0, 750.0, 0.4, 512, 512)
    same, cam2 = to_training_scale(mask, fine, 0.4)
    assert same is mask and cam2 is fine


def test_a_second_training_run_refuses_a_folder_another_run_holds(tmp_path):
    from stages.sbp.train import TrainConfig, lock_run_dir, train

    held = lock_run_dir(tmp_path)
    with pytest.raises(UserError, match="another training run is still writing"):
        train(tmp_path / "no_cases", tmp_path, TrainConfig(steps=1))  # refused before it reads any case
    held.close()
    again = lock_run_dir(tmp_path)  # free once the first run has let go
    assert again is not None
    again.close()

"""Every run of the same tree: the correspondence method on three or more views (stages.twoview.multiview),
the held-out check on subsets of N runs, and `autocar reconstruct` with further runs."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stages.calibration.synthetic import synthetic_tree
from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.twoview import match_views
from stages.twoview.method import Polyline3D
from stages.twoview.multiview import _keep_on_vessels, drop_contradicted, multiview_polylines, view_evidence

PHANTOM = Path(__file__).resolve().parents[2] / "shared" / "data" / "phantom_xa"
needs_phantom = pytest.mark.skipif(not (PHANTOM / "IM1.dcm").exists(),
                                   reason=f"the real phantom runs are not in {PHANTOM}")


def _tube_mask(cam, points, radius_mm):
    from skimage.draw import disk

    mask = np.zeros((cam.rows, cam.cols), bool)
    rc, depth = cam.project(points, return_depth=True)
    for (r, c), s in zip(rc, depth / cam.K[0, 0]):
        rr, cc = disk((r, c), radius_mm / s, shape=mask.shape)
        mask[rr, cc] = True
    return mask


def _scene(seed=3):
    tree = synthetic_tree(seed=seed, n_branches=9)
    cams = [Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512), Camera.from_carm(-40, 0, 1000, 760, 0.3, 512, 512),
            Camera.from_carm(0, -35, 1050, 740, 0.3, 512, 512)]
    return tree, cams, [_tube_mask(c, tree, 1.2) for c in cams]


def _errors(polylines, truth):
    pts = np.concatenate([p.points for p in polylines])
    recon_to_truth = cKDTree(truth).query(pts)[0]
    truth_to_recon = cKDTree(pts).query(truth)[0]
    return recon_to_truth, truth_to_recon


def test_a_stretch_two_other_pairs_place_elsewhere_is_dropped():
    """One pair's stretch whose pixels in two views the other pairs explain with vessels elsewhere in 3D, and no
    other pair corroborates, goes; the vessels those pairs agree on stay, and so does a vessel only one pair found."""
    _, cams, _ = _scene()
    t = np.linspace(0.0, 1.0, 40)[:, None]
    vessel = t * np.array([30.0, 10.0, 5.0])

    def along_rays(cam, X, mm):  # the same pixels in this view, mm deeper
        return X + mm * cam.rays(cam.project(X))[1]

    ghost = along_rays(cams[0], vessel, 12.0)  # view 1 sees it on `vessel`
    other = along_rays(cams[1], ghost, 12.0)  # view 2 sees it on `other`
    lone = vessel + np.array([0.0, 0.0, 40.0])

    def line(X):
        return Polyline3D(X, np.ones(len(X)), np.ones(len(X), bool))

    kept = drop_contradicted([line(ghost), line(lone), line(vessel), line(other), line(vessel + 0.3),
                              line(other - 0.3)], [0, 0, 1, 1, 2, 2], cams)
    pts = np.concatenate([p.points for p in kept])
    near = cKDTree(pts)
    assert np.all(near.query(ghost)[0] > 5.0)
    for X in (lone, vessel, other):
        assert np.all(near.query(X)[0] < 1e-9)
    assert len(pts) == 5 * len(vessel)


def test_a_third_view_removes_the_ghosts_two_views_make():
    truth, cams, masks = _scene()
    two = match_views(masks[0], masks[1], cams[0], cams[1]).polylines
    three = multiview_polylines(masks, cams)
    ghost2, _ = _errors(two, truth)
    ghost3, found3 = _errors(three, truth)
    # two views of a 9-branch tree: some matched points are ghosts (> 2 mm from any vessel)
    assert (ghost2 > 2.0).mean() > 0.02
    # three views: most of them go (10.7 % → 2.9 % here: what is left projects onto vessels in all three views),
    # and the tree is still found
    assert (ghost3 > 2.0).mean() < 0.4 * (ghost2 > 2.0).mean()
    assert np.median(ghost3) < 0.3
    assert (found3 < 1.5).mean() > 0.85


def test_a_view_of_another_tree_is_left_out_and_said_so():
    truth, cams, masks = _scene()
    other, _, _ = _scene(seed=11)
    wrong = _tube_mask(cams[2], other, 1.2)  # the third run shows another tree (e.g. the other coronary)
    report = {}
    got = multiview_polylines([masks[0], masks[1], wrong], cams, report=report)
    assert report[2]["used"] is False and report[2]["consistency"] < 0.45
    ref = match_views(masks[0], masks[1], cams[0], cams[1]).polylines
    assert len(got) == len(ref) and all(np.array_equal(a.points, b.points) for a, b in zip(ref, got))
    report = {}
    multiview_polylines(masks, cams, report=report)
    assert report[2]["used"] is True and report[2]["consistency"] > 0.6


def test_a_displaced_further_view_is_shifted_back_onto_the_first_two():
    truth, cams, masks = _scene()
    moved = _tube_mask(cams[2], truth + [0.0, 0.0, 4.0], 1.2)  # breathing moved the heart 4 mm towards the head
    report = {}
    got = multiview_polylines([masks[0], masks[1], moved], cams, report=report)
    assert report[2]["used"]
    ghost, found = _errors(got, truth)
    assert np.median(ghost) < 0.35 and (found < 1.5).mean() > 0.85


def _breathing_scene(offset_b, offset_c):
    """The test scene with runs B and C displaced by ``offset_b`` / ``offset_c`` (mm) from run A, view B aligned
    across its epipolar lines (as `reconstruct` aligns it): (truth, masks, cameras, the shift (px) view B then lacks
    along its epipolar lines)."""
    truth, cams, _ = _scene()
    offsets = [np.zeros(3), np.asarray(offset_b, float), np.asarray(offset_c, float)]
    masks = [_tube_mask(cam, truth + t, 1.2) for cam, t in zip(cams, offsets)]
    centre = truth.mean(axis=0)
    seen = cams[1].project((centre + offsets[1])[None])[0] - cams[1].project(centre[None])[0]
    epipolar = cams[1].project((centre + cams[0].view_dir)[None])[0] - cams[1].project(centre[None])[0]
    epipolar /= np.linalg.norm(epipolar)
    along = (seen @ epipolar) * epipolar
    return truth, masks, [cams[0], cams[1].shifted(*(seen - along)), cams[2]], along


def test_breathing_between_the_runs_does_not_become_depth(monkeypatch):
    """Runs B and C see the heart displaced by breathing (mostly towards the head). Two views observe the part of
    B's displacement across its epipolar lines (`reconstruct` aligns it) but cannot tell the part along them from
    depth; the third view and the breathing prior can: view B is moved along its epipolar lines and the model
    lands where run A sees the tree."""
    import stages.twoview.multiview as multiview

    truth, masks, cams, along = _breathing_scene([0.0, 1.5, 6.0], [0.0, 0.4, 1.5])
    report = {}
    got = multiview_polylines(masks, cams, report=report)
    monkeypatch.setattr(multiview, "MIN_BREATHING_CORRECTION_PX", np.inf)
    uncorrected = multiview_polylines(masks, cams)
    err, found = _errors(got, truth)
    err0, _ = _errors(uncorrected, truth)
    # moved by 6.5 px where it lacked 5.4 px (the prior takes run A's offset for one draw of the breathing, as every
    # run's; here it happens to be zero); the model 1.03 mm from the tree without, 0.44 mm with
    assert np.linalg.norm(np.subtract(report[1]["shift_px"], along)) < 1.5
    assert np.median(err) < 0.5 * np.median(err0) and np.median(err) < 0.5 and (found < 1.5).mean() > 0.9


def test_runs_displaced_beyond_the_further_views_search_are_found_by_moving_the_second_view(monkeypatch):
    """Runs B and C both see the heart 14 mm further towards the head than run A. B's displacement along its epipolar
    lines becomes depth, and the model lands so far off that run C's shift onto it lies beyond the search, so run C
    measures nothing; moving view B along its epipolar lines first (a few steps) brings run C within reach."""
    import stages.twoview.multiview as multiview

    truth, masks, cams, along = _breathing_scene([0.0, 2.0, 14.0], [0.0, 2.0, 14.0])
    report = {}
    got = multiview_polylines(masks, cams, report=report)
    monkeypatch.setattr(multiview, "ALONG_SEARCH_PX", ())
    unsearched = multiview_polylines(masks, cams)
    err, _ = _errors(got, truth)
    err0, _ = _errors(unsearched, truth)
    # moved by 15.2 px of the 16.7 px it lacked; the model 3.2 mm from the tree without the search, 1.0 mm with
    assert np.linalg.norm(np.subtract(report[1]["shift_px"], along)) < 3.0
    assert np.median(err) < 0.4 * np.median(err0) and np.median(err) < 1.5


def test_second_view_misaligned_across_its_epipolar_lines_is_placed_on_the_further_views_model(monkeypatch):
    """View B's two-view alignment missed 5 px across its epipolar lines (wide vessels give flat crossing profiles);
    the model of view A with view C, which agrees with it, shows where view B's vessels are: view B is moved across
    and the model lands on the tree."""
    import stages.twoview.multiview as multiview

    truth, masks, cams, _ = _breathing_scene([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    centre = truth.mean(axis=0)
    epipolar = cams[1].project((centre + cams[0].view_dir)[None])[0] - cams[1].project(centre[None])[0]
    across = np.array([-epipolar[1], epipolar[0]]) / np.linalg.norm(epipolar)
    cams = [cams[0], cams[1].shifted(*(-5.0 * across)), cams[2]]
    report = {}
    got = multiview_polylines(masks, cams, report=report)
    monkeypatch.setattr(multiview, "MIN_ACROSS_CORRECTION_PX", np.inf)
    uncorrected = multiview_polylines(masks, cams)
    err, found = _errors(got, truth)
    err0, _ = _errors(uncorrected, truth)
    assert np.linalg.norm(np.subtract(report[1]["shift_px"], 5.0 * across)) < 1.5
    assert np.median(err) < 0.5 and np.median(err) < 0.6 * np.median(err0) and (found < 1.5).mean() > 0.9


def test_two_views_are_exactly_the_two_view_method():
    truth, cams, masks = _scene(seed=5)
    ref = match_views(masks[0], masks[1], cams[0], cams[1]).polylines
    got = multiview_polylines(masks[:2], cams[:2])
    assert len(ref) == len(got)
    assert all(np.array_equal(a.points, b.points) and np.array_equal(a.radius, b.radius) for a, b in zip(ref, got))


def test_view_evidence_is_high_on_the_vessel_and_neutral_outside_the_image():
    truth, cams, masks = _scene()
    from scipy import ndimage

    ev = view_evidence([cams[2]], [ndimage.distance_transform_edt(~masks[2])])
    assert ev(truth).min() > 0.99
    off = truth + np.array([0.0, 0.0, 8.0])  # 8 mm away: off the vessels of view 3 almost everywhere
    assert np.median(ev(off)) < 0.2
    far = np.array([[0.0, 0.0, 900.0]])  # projects outside view 3: it says nothing
    assert ev(far)[0] == 1.0


def test_a_point_outside_a_view_away_from_its_exiting_vessels_is_cut():
    """A pooled stretch on the vessels of the two views that found it but projecting outside a third view's image
    goes, unless a vessel of that view leaves the image where the stretch would enter it."""
    from scipy import ndimage

    from stages.core.geometry import outside_away_from_exits

    truth, cams, _ = _scene()
    third = Camera.from_carm(45, -30, 1100, 750, 0.3, 448, 448)  # a tighter field: the tree inside, the stretch not
    stretch = np.array([0.0, -60.0, 40.0]) + np.c_[np.linspace(0, 20, 41), np.zeros(41), np.zeros(41)]
    assert third.in_image(third.project(truth), margin=8).all()
    assert not third.in_image(third.project(stretch)).any()
    cameras = cams[:2] + [third]
    masks = [_tube_mask(c, np.vstack([truth, stretch]), 1.2) for c in cams[:2]] + [_tube_mask(third, truth, 1.2)]

    def kept(masks):
        lines = [Polyline3D(X, np.ones(len(X)), np.ones(len(X), bool)) for X in (truth, stretch)]
        out = _keep_on_vessels(lines, cameras, masks, [ndimage.distance_transform_edt(~m) for m in masks], 3.0)
        return np.concatenate([p.points for p in out])

    pts = kept(masks)
    assert len(pts) == len(truth) and np.allclose(pts, truth)
    leaving = masks[2].copy()  # a vessel of the third view meets the border where the stretch would enter
    rc = np.rint(np.clip(third.project(stretch), 0, 447)).astype(int)
    leaving[rc[:, 0], rc[:, 1]] = True
    assert len(kept(masks[:2] + [leaving])) == len(truth) + len(stretch)
    # inside the image, or within the rim just outside it (a vessel may leave the segmented field there), nothing
    # is judged; beyond, with no vessel of the view reaching the rim, everything is
    assert not outside_away_from_exits(third, masks[2], third.project(truth)).any()
    assert outside_away_from_exits(third, np.zeros_like(masks[2]), np.array([[-5.0, 10.0], [-40.0, 10.0]])).tolist() \
        == [False, True]


def test_bad_view_sets_are_refused_clearly():
    truth, cams, masks = _scene()
    with pytest.raises(UserError, match="at least two views"):
        multiview_polylines(masks[:1], cams[:1])
    with pytest.raises(UserError, match="view 3's vessel mask is empty"):
        multiview_polylines([masks[0], masks[1], np.zeros_like(masks[2])], cams)


def test_held_out_subsets_are_every_n_subset_or_a_seeded_sample():
    from stages.evaluate.heldout import held_out_subsets

    assert len(held_out_subsets(8, 3)) == 56
    sample = held_out_subsets(8, 3, max_subsets=20, seed=0)
    assert len(sample) == 20 and sample == held_out_subsets(8, 3, max_subsets=20, seed=0)
    assert all(len(set(s)) == 3 for s in sample)
    with pytest.raises(UserError, match="left out"):
        held_out_subsets(4, 4)


def test_a_two_run_method_refuses_further_runs(tmp_path):
    from stages.reconstruct import reconstruct

    ex = Path(__file__).resolve().parents[1] / "examples"
    with pytest.raises(UserError, match="reconstructs from two runs"):
        reconstruct(ex / "run_a.dcm", ex / "run_b.dcm", tmp_path / "out", method="visual-hull",
                    more_runs=[ex / "run_a.dcm"])
    assert not (tmp_path / "out").exists()


def test_a_run_given_twice_is_refused(cli, tmp_path):
    ex = Path(__file__).resolve().parents[1] / "examples"
    r = cli("reconstruct", str(ex / "run_a.dcm"), str(ex / "run_b.dcm"), str(ex / "run_a.dcm"), "-o", str(tmp_path / "o"))
    assert r.exit_code != 0
    assert "error:" in r.output and "the same run as" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "o").exists()


@needs_phantom
def test_three_phantom_runs_give_one_tree_without_far_pieces(tmp_path):
    from stages.reconstruct import reconstruct

    out = tmp_path / "r3"
    summary = reconstruct(PHANTOM / "IM1.dcm", PHANTOM / "IM3.dcm", out, k=1, qca=False,
                          more_runs=[PHANTOM / "IM6.dcm"])
    pieces = summary["quality"]["frames"][0]["pieces"]
    # two views of these runs gave 23 pieces, 14 of them > 10 mm from the tree, before graph-opt joined pieces
    assert len(pieces) <= 10
    assert all(p["distance_mm"] <= 10.0 for p in pieces[1:])
    assert pieces[0]["length_mm"] > 600  # the phantom's tree is about 785 mm of centreline
    assert [r["run"] for r in summary["runs"]] == ["run A", "run B", "run C"]
    assert summary["runs"][2]["frames"] == [summary["runs"][2]["frames"][0]] and summary["runs"][2]["frames"][0] is not None
    assert summary["runs"][2]["table_offset_mm"] is not None  # IM6 was taken with the table moved
    assert summary["runs"][2]["consistency"][0] > 0.5  # the same tree: most of A + B's model lies on its vessels
    assert (out / "masks_c.zarr").exists()
    # the third view's reprojection is checked like the other two
    assert set(summary["quality"]["frames"][0]["reprojection_mm"]) == {"a", "b", "c"}
    assert max(summary["quality"]["frames"][0]["reprojection_mm"].values()) < 1.0
    saved = json.loads((out / "summary.json").read_text())
    assert saved["parameters"]["more_runs"] == [str(PHANTOM / "IM6.dcm")]


@needs_phantom
def test_held_out_check_from_three_views(tmp_path):
    from stages.evaluate.heldout import run_heldout

    res = run_heldout(PHANTOM, method="default", seg_method="unet", views_per_subset=3, max_subsets=1,
                      fit_pose=False)
    assert res["views_per_subset"] == 3 and len(res["subsets"]) == 1
    rows = res["rows"]
    assert len(rows) == 5 and all(r["pair"].count("+") == 2 for r in rows)
    assert {r["heldout"] for r in rows}.isdisjoint(res["subsets"][0])
    s = res["summary"]["nominal"]
    # two views of the phantom: about 0.84 coverage, 2.8 mm (nominal poses)
    assert s["coverage"]["mean"] > 0.85 and s["distance_mm"]["mean"] < 2.2


def test_three_run_evaluation_needs_run_c_and_render_says_where_runs_apply(tmp_path, cli):
    from stages.evaluate.end_to_end import case_key, case_runs

    case = tmp_path / "case_0000001"
    case.mkdir()
    for name in ("run_a.dcm", "run_b.dcm"):
        (case / name).write_bytes(b"x")
    assert case_runs(case) == [case / "run_a.dcm", case / "run_b.dcm"]
    with pytest.raises(UserError, match="run_c.dcm: missing"):
        case_runs(case, 3)
    (case / "run_c.dcm").write_bytes(b"y")
    # a three-run reconstruction is cached apart from the two-run one
    assert case_key(case, "correspondence", None, 3) != case_key(case, "correspondence", None)
    r = cli("render", "se", "--runs", "3", "-o", str(tmp_path / "se"))
    assert r.exit_code != 0 and "only render re makes more than two runs" in r.output

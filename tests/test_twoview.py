"""Explicit two-view correspondence (stages.twoview) on analytic two-view geometry."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.twoview import Centreline2D, correspondence_prediction, extract_centreline, match_views
from stages.core.geometry import epipolar_angles, epipolar_frame
from stages.twoview.epipolar import candidates, triangulate
from stages.twoview.method import kept_points
from stages.twoview.select import DirectionalMatch, match_direction


def _cams():
    return (Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512), Camera.from_carm(-40, 0, 1000, 760, 0.3, 512, 512))


def _tube_mask(cam, points, radius):
    from skimage.draw import disk

    mask = np.zeros((cam.rows, cam.cols), bool)
    rc, depth = cam.project(points, return_depth=True)
    mm_per_px = depth / cam.K[0, 0]
    for (r, c), rad, s in zip(rc, radius, mm_per_px):
        rr, cc = disk((r, c), rad / s, shape=mask.shape)
        mask[rr, cc] = True
    return mask


def _helix(n=1500):
    t = np.linspace(0, 1, n)
    return np.stack([40 * np.cos(3 * t), 40 * np.sin(3 * t), 60 * t - 30], 1), 1.4 - 0.6 * t


def _exact_centreline(cam, points):
    """A Centreline2D made of the exact projections of a 3D curve (one branch)."""
    rc = cam.project(points)
    tan = np.gradient(rc, axis=0)
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    return Centreline2D(rc, tan, np.full(len(rc), 3.0), np.zeros(len(rc), np.int32), np.array([[0, 1]]), (cam.rows, cam.cols),
                        rc[[0, -1]])


def test_candidates_contain_the_exact_partner_and_triangulation_recovers_the_curve():
    cam_a, cam_b = _cams()
    P, _ = _helix(600)
    cl_a, cl_b = _exact_centreline(cam_a, P[::3]), _exact_centreline(cam_b, P)
    frame = epipolar_frame(cam_a, cam_b)
    th_a, th_b = epipolar_angles(cam_a, cl_a.points, frame), epipolar_angles(cam_b, cam_b.project(P[::3]), frame)
    assert np.allclose(th_a, th_b, atol=1e-9)  # the same 3D point has the same epipolar-plane angle in both views
    cand = candidates(frame, cl_a, cam_a, cl_b, cam_b, tol_px=1.0)
    X, gap = triangulate(cam_a, cl_a.points[cand.query], cam_b, cand.b_pos)
    truth = P[::3][cand.query]
    err = np.linalg.norm(X - truth, axis=1)
    best = np.full(len(cl_a), np.inf)
    np.minimum.at(best, cand.query, err)
    well_posed = np.isfinite(best)
    assert well_posed.mean() > 0.95
    # the exact partner is among the candidates: sub-0.05 mm where the curve crosses the epipolar line
    assert np.median(best[well_posed]) < 0.02 and np.percentile(best[well_posed], 90) < 0.2
    assert np.all(gap[err < 0.05] < 0.05)


def test_centreline_radius_is_subpixel_on_a_straight_tube():
    mask = np.zeros((200, 200), bool)
    rr, cc = np.mgrid[:200, :200]
    d = np.abs((rr - 100) * np.cos(0.3) - (cc - 100) * np.sin(0.3))  # a tilted band of half-width 4.3 px
    mask[(d <= 4.3) & (rr > 20) & (rr < 180)] = True
    cl = extract_centreline(mask, drop_catheter=False)  # (straight from edge to edge: catheter-like)
    assert cl.n_branches == 1 and len(cl) > 100
    mid = cl.radius_px[20:-20]
    assert abs(np.median(mid) - 4.3) < 0.35
    inner = cl.points[15:-15]  # the ends bend towards the cut corners of the band
    assert np.all(np.abs((inner[:, 0] - 100) * np.cos(0.3) - (inner[:, 1] - 100) * np.sin(0.3)) < 0.5)


def test_helix_is_recovered_with_its_radius():
    cam_a, cam_b = _cams()
    P, R = _helix()
    m = match_views(_tube_mask(cam_a, P, R), _tube_mask(cam_b, P, R), cam_a, cam_b)
    d, j = cKDTree(P).query(m.points_3d)
    assert np.median(d) < 0.2 and np.percentile(d, 90) < 1.0
    assert np.abs(m.radius_mm - R[j]).mean() < 0.1
    dd, _ = cKDTree(m.points_3d).query(P)
    assert (dd < 1.0).mean() > 0.9
    assert m.confirmed.mean() > 0.85  # both directions agree


def test_vessels_crossing_in_one_view_are_both_recovered():
    cam_a, cam_b = _cams()
    t = np.linspace(0, 1, 800)
    # two straight vessels at different depths whose projections cross in view A
    c1 = np.stack([-35 + 70 * t, 10 * t, 20 + 0 * t], 1)
    centre = c1[400]
    ray = centre - cam_a.source
    ray /= np.linalg.norm(ray)
    c2_mid = centre + 25 * ray  # same pixel in view A, 25 mm deeper
    perp = np.cross(ray, c1[-1] - c1[0])
    perp /= np.linalg.norm(perp)
    c2 = c2_mid + (t[:, None] - 0.5) * 45 * perp  # (ends inside the image: straight from the edge is a catheter)
    P, R = np.vstack([c1, c2]), np.r_[np.full(800, 1.2), np.full(800, 0.9)]
    rc1, rc2 = cam_a.project(c1[400:401]), cam_a.project(c2[400:401])
    assert np.linalg.norm(rc1 - rc2) < 1.0  # they do cross in view A
    m = match_views(_tube_mask(cam_a, P, R), _tube_mask(cam_b, P, R), cam_a, cam_b)
    for curve in (c1, c2):
        dd, _ = cKDTree(m.points_3d).query(curve[60:-60])
        assert (dd < 1.0).mean() > 0.85
    d, _ = cKDTree(P).query(m.points_3d)
    assert np.percentile(d, 90) < 1.0


def test_ghost_of_one_direction_is_dropped_by_both_way_agreement():
    cam_a, cam_b = _cams()
    P, R = _helix()
    mask_a, mask_b = _tube_mask(cam_a, P, R), _tube_mask(cam_b, P, R)
    cl_a, cl_b = extract_centreline(mask_a), extract_centreline(mask_b)
    ab = match_direction(cl_a, cam_a, cl_b, cam_b)
    ba = match_direction(cl_b, cam_b, cl_a, cam_a)
    # A→B and B→A describe the same curve: each direction's 3D points lie on the other's
    da, _ = cKDTree(ba.points_3d[ba.matched]).query(ab.points_3d[ab.matched])
    assert np.median(da) < 0.3
    # a spurious blob in view B only (no counterpart in A) creates nothing that survives
    ghost_b = mask_b.copy()
    ghost_b[40:46, 40:200] = True
    m = match_views(mask_a, ghost_b, cam_a, cam_b)
    d, _ = cKDTree(P).query(m.points_3d)
    assert np.percentile(d, 95) < 2.0


def test_points_found_one_way_only_stay_near_the_confirmed_tree_and_go_far_from_it():
    # five points of one direction: confirmed; unconfirmed and cheap 5 mm from the confirmed tree (a vessel
    # overlapping another in the other view); unconfirmed and cheap 35 mm away (an epipolar coincidence);
    # unconfirmed and costly next to the tree; no partner at all
    points = np.array([[0.0, 0, 0], [5, 0, 0], [35, 0, 0], [2, 0, 0], [np.nan] * 3])
    n = len(points)
    match = DirectionalMatch(np.zeros((n, 2)), np.zeros(n, int), points, np.ones(n), np.ones(n),
                             np.array([3.0, 0.4, 0.1, 1.5, np.nan]), np.ones(n))
    confirmed = np.array([True, False, False, False, False])
    anchors = np.array([[0.0, 0, 0], [-10, 0, 0]])
    kept = kept_points(match, confirmed, anchors, max_cost=1.0, reach_mm=20.0)
    assert kept.tolist() == [True, True, False, False, False]
    # with no confirmed point at all nothing found one way only survives
    assert not kept_points(match, np.zeros(n, bool), np.zeros((0, 3)), 1.0, 20.0).any()


def test_prediction_is_a_tube_on_the_half_millimetre_grid():
    cam_a, cam_b = _cams()
    P, R = _helix()
    vox = correspondence_prediction(_tube_mask(cam_a, P, R), _tube_mask(cam_b, P, R), cam_a, cam_b)
    assert vox.voxel_size == 0.5 and set(vox.features) == {"occupancy", "centreness"}
    length = np.linalg.norm(np.diff(P, axis=0), axis=1).sum()
    volume = (np.pi * R ** 2).mean() * length
    assert 0.75 < len(vox) * 0.125 / volume < 1.3
    dist, _ = cKDTree(P).query(vox.world_points())
    assert np.all(dist < R.max() + 1.0)


def test_bad_input_is_refused_clearly():
    cam_a, cam_b = _cams()
    P, R = _helix(300)
    mask = _tube_mask(cam_a, P, R)
    with pytest.raises(UserError, match="view A's vessel mask is empty"):
        correspondence_prediction(np.zeros_like(mask), _tube_mask(cam_b, P, R), cam_a, cam_b)
    with pytest.raises(UserError, match="view B's vessel mask is empty"):
        correspondence_prediction(mask, np.zeros_like(mask), cam_a, cam_b)
    near = Camera.from_carm(33, 22, 1100, 750, 0.3, 512, 512)
    with pytest.raises(UserError, match="apart"):
        correspondence_prediction(mask, _tube_mask(near, P, R), cam_a, near)
    with pytest.raises(UserError, match="do not match the cameras"):
        correspondence_prediction(mask[:100], mask, cam_a, cam_b)


def test_catheter_entering_the_image_is_left_out_and_straight_vessels_inside_stay():
    """A straight band from the image edge across a vessel is a catheter (stages.core.catheter): its pieces on
    both sides of the crossing go; the curved vessel it crosses and a straight vessel inside the image stay."""
    rr, cc = np.mgrid[:300, :300]
    arc = np.abs(np.hypot(rr - 300, cc - 150) - 150) <= 3.0  # a vessel curving across the lower half
    catheter = (np.abs((cc - 60) - 0.25 * rr) <= 3.0) & (rr < 290)  # from the top edge down, across the arc
    inner = (np.abs(rr - 100) <= 2.5) & (cc > 150) & (cc < 260)  # straight but well inside the image
    mask = arc | catheter | inner
    cl = extract_centreline(mask)
    off_line = np.abs((cl.points[:, 1] - 60) - 0.25 * cl.points[:, 0]) / np.hypot(1, 0.25)
    on_arc = np.abs(np.hypot(cl.points[:, 0] - 300, cl.points[:, 1] - 150) - 150) < 2.0
    # nothing of the catheter left beyond the crossing's junction
    assert np.all((off_line > 2.0) | on_arc | (np.hypot(cl.points[:, 0] - 160, cl.points[:, 1] - 100) < 12))
    arc_px = np.argwhere(arc & (np.hypot(rr - 300, cc - 150) - 150 < 0.7) & (np.hypot(rr - 300, cc - 150) > 149.3))
    assert np.mean(cKDTree(cl.points).query(arc_px)[0] < 1.5) > 0.9
    assert np.sum(np.abs(cl.points[:, 0] - 100) < 1.0) > 90  # the straight inner vessel (110 px) stays
    # without the rule the catheter is a branch of its own on each side of the arc
    assert np.sum(np.abs((extract_centreline(mask, drop_catheter=False).points[:, 1] - 60)
                         - 0.25 * extract_centreline(mask, drop_catheter=False).points[:, 0]) < 1.0) > 150


def test_centreline_of_a_vessel_loop_stays_on_the_vessels():
    """Vessels crossing in a projection enclose background: the enclosed hole must stay open (filling it
    made a blob whose skeleton ran through the background, half the centreline lost on data-se)."""
    yy, xx = np.mgrid[:200, :200]
    rho = np.hypot(yy - 100, xx - 100)
    ring = np.abs(rho - 50) <= 3.0
    ring[100, 100] = False
    pinhole = ring.copy()
    pinhole[100, 150] = False  # a one-pixel hole inside the vessel is filled
    cl = extract_centreline(pinhole)
    d = np.abs(np.hypot(cl.points[:, 0] - 100, cl.points[:, 1] - 100) - 50)
    assert len(cl) > 250  # ≈ 2π·50 = 314 px of centreline
    assert np.percentile(d, 95) < 1.0


def test_the_evidence_predictor_gives_each_thread_its_own_masks_centrelines():
    """`reconstruct --threads N` predicts key frames in threads with one correspondence predictor, which extracts
    a mask pair's 2D centrelines once for all of view B's cameras: each call must get its own masks' centrelines."""
    from concurrent.futures import ThreadPoolExecutor

    from stages.methods3d import load_evidence_predictor

    cam_a, cam_b = _cams()
    P, R = _helix(600)
    pairs = [(_tube_mask(cam_a, P + [dx, 0, 0], R), _tube_mask(cam_b, P + [dx, 0, 0], R)) for dx in (-8.0, 0.0, 8.0)] * 2
    alone = [load_evidence_predictor("correspondence")(a, b, cam_a, [cam_b])[0] for a, b in pairs]
    predict = load_evidence_predictor("correspondence")
    with ThreadPoolExecutor(3) as pool:
        together = list(pool.map(lambda ab: predict(ab[0], ab[1], cam_a, [cam_b])[0], pairs))
    for v1, v2 in zip(alone, together):
        assert np.array_equal(v1.coords, v2.coords)
    assert len({len(v) for v in alone}) > 1 or not np.array_equal(alone[0].coords, alone[1].coords)


def test_tubes_become_exactly_the_voxels_whose_centre_lies_inside_them():
    """The rasteriser's candidate search (a ball of offsets around every other sample) misses no voxel: against a
    brute-force test of every grid voxel near random tubes of radius 0.1–4.5 mm."""
    from stages.twoview.method import Polyline3D, tubes_to_voxels

    rng = np.random.default_rng(7)
    for _ in range(8):
        lines = []
        for _ in range(3):
            n = int(rng.integers(3, 25))
            pts = np.cumsum(rng.normal(0, 1.5, (n, 3)), axis=0) + rng.uniform(-10, 10, 3)
            lines.append(Polyline3D(pts, np.clip(rng.uniform(0.2, 4.5) + rng.normal(0, 0.3, n), 0.1, None), None))
        vox = tubes_to_voxels(lines)
        # the same dense samples the rasteriser uses (every 0.2 mm), then every grid voxel of their bounding box
        samples, radii = [], []
        for pl in lines:
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pl.points, axis=0), axis=1))]
            t = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / 0.2)) + 1, 2))
            samples.append(np.stack([np.interp(t, s, pl.points[:, k]) for k in range(3)], axis=1))
            radii.append(np.interp(t, s, pl.radius))
        P, R = np.concatenate(samples), np.concatenate(radii)
        lo = np.floor((P.min(0) - R.max()) / 0.5).astype(int) - 1
        hi = np.ceil((P.max(0) + R.max()) / 0.5).astype(int) + 1
        grid = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
        d, j = cKDTree(P).query(grid * 0.5, k=8)
        inside = (d / R[j]).min(1) < 1.0
        assert set(map(tuple, grid[inside])) == set(map(tuple, vox.coords.tolist()))


def test_tree_extent_is_the_trees_centre_and_width_and_costs_only_implausible_depths():
    from stages.twoview.select import _beyond_extent, tree_extent

    cam_a, cam_b = _cams()
    P, _ = _helix()
    P = P + [12.0, -8.0, 5.0]  # a tree off the isocentre
    cl_a, cl_b = _exact_centreline(cam_a, P), _exact_centreline(cam_b, P)
    centre, radius = tree_extent(cl_a, cam_a, cl_b, cam_b)
    assert np.linalg.norm(centre - P.mean(0)) < 1.0  # the centroids' rays meet near the curve's centroid
    lateral_mm = max(np.percentile(np.linalg.norm(cam.project(P) - cam.project(P).mean(0), axis=1), 99)
                     * cam.isocentre_spacing for cam in (cam_a, cam_b))
    assert abs(radius - lateral_mm) < 0.1 * lateral_mm  # the wider view's extent, in mm near the isocentre
    # the tree itself is never implausible; the same points pushed 80 mm along view A's rays are
    assert np.all(_beyond_extent(P, (centre, radius), 1.1, (cam_a, cam_b)) == 0.0)
    origins, dirs = cam_a.rays(cam_a.project(P))
    deeper = P + 80.0 * dirs
    assert np.allclose(cam_a.project(deeper), cam_a.project(P), atol=1e-6)  # view A cannot tell them apart
    assert np.all(_beyond_extent(deeper, (centre, radius), 1.1, (cam_a, cam_b)) > 0.0)

"""Visual hull: coarse-to-fine result equals brute force over every voxel; it contains the object."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.core.geometry import Camera
from stages.visual_hull import project_to_mask, visual_hull


def cameras():
    a = Camera.from_carm(30.0, 0.0, 1000.0, 750.0, 0.3, 256, 256)
    b = Camera.from_carm(-40.0, 20.0, 1000.0, 750.0, 0.3, 256, 256)
    return a, b


def random_masks(seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        noise = ndimage.gaussian_filter(rng.normal(size=(256, 256)), 3.0)
        m = noise > np.percentile(noise, 80)
        m[:, :60] = m[:, -60:] = False  # keep the hull inside the ±20 mm test box
        m[:60] = m[-60:] = False
        out.append(m)
    return out


def brute_force(masks, cams, half, vs):
    n = int(round(2 * half / vs)) + 1
    g = np.arange(n)
    idx = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = -half + idx * vs
    keep = np.ones(len(pts), bool)
    for m, cam in zip(masks, cams):
        rc = np.rint(cam.project(pts))
        ok = (rc[:, 0] >= 0) & (rc[:, 0] < cam.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < cam.cols)
        hit = np.zeros(len(pts), bool)
        hit[ok] = m[rc[ok, 0].astype(int), rc[ok, 1].astype(int)]
        keep &= hit
    return {tuple(x) for x in idx[keep].tolist()}


def test_coarse_to_fine_equals_brute_force():
    cams = cameras()
    masks = random_masks(0)
    hull = visual_hull(masks, cams, voxel_size=0.5, half_extent_mm=20.0, levels=3)
    assert np.allclose(hull.origin, -20.0)
    got = {tuple(x) for x in hull.coords.tolist()}
    want = brute_force(masks, cams, 20.0, 0.5)
    assert len(want) > 1000
    assert got == want


def test_hull_contains_the_object_and_is_written_with_occupancy():
    cams = cameras()
    # a curved tube of radius 1.2 mm through the isocentre region
    t = np.linspace(-25, 25, 400)
    axis = np.stack([t, 8 * np.sin(t / 10), 0.3 * t], 1)
    g = np.arange(-30, 30.5, 0.5)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(axis).query(grid, distance_upper_bound=2.0)
    tube = grid[d <= 1.2]
    masks = [project_to_mask(tube, c, dilate_px=1) for c in cams]
    hull = visual_hull(masks, cams)
    hull_set = {tuple(x) for x in np.rint((hull.world_points()) / 0.5).astype(int).tolist()}
    tube_set = {tuple(x) for x in np.rint(tube / 0.5).astype(int).tolist()}
    assert tube_set <= hull_set  # the object is inside its visual hull
    assert len(hull) < 20 * len(tube)  # and the hull is a thin shell around it, not the box
    assert np.all(hull.features["occupancy"] == 1.0)


def test_empty_mask_gives_empty_hull():
    cams = cameras()
    hull = visual_hull([np.zeros((256, 256), bool), np.ones((256, 256), bool)], cams, half_extent_mm=10)
    assert len(hull) == 0

"""Synthetic X-ray engine: silhouettes vs exact ray casting, path lengths, warps, heart motion, pairs."""

from __future__ import annotations

import numpy as np
import pytest

from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.poses import PoseModel
from stages.render.augment import Warp2D, random_warp
from stages.render.motion import HeartMotion, contraction, sample_motion
from stages.render.pairs import render_pair
from stages.render.phantom import tube_case
from stages.render.raster import boundary_disagreement, rasterise_mask, rasterise_path_length, raycast_mask


@pytest.fixture(scope="module")
def cases():
    return [tube_case(s) for s in (11, 12, 13)]


@pytest.fixture(scope="module")
def pose_model():
    return PoseModel.default(seed=0)


def test_silhouette_agrees_with_mesh_raycast_on_20_pairs(cases, pose_model):
    """The fast silhouette (triangle raster of the prepared mesh) vs Möller–Trumbore ray casting."""
    rng = np.random.default_rng(2024)
    worst = []
    for i in range(20):
        case = cases[i % len(cases)]
        pa, pb = pose_model.sample_pair(rng)
        pose = pa if i % 2 else pb
        size = 512 if i < 4 else 256
        cam = pose.camera(size, size).shifted(*rng.uniform(-5, 5, 2))
        V = case.vertices.astype(float) + rng.uniform(-8, 8, 3)
        fast = rasterise_mask(V, case.faces, cam)
        ref = raycast_mask(V, case.faces, cam)
        assert ref.sum() > 200, "the tree must be in view for the comparison to mean anything"
        d = boundary_disagreement(fast, ref)
        worst.append(d["max_px"])
        assert d["max_px"] <= 0.5, (i, d)
    assert max(worst) <= 0.5


def test_boundary_metric_detects_a_shifted_silhouette(cases, pose_model):
    case = cases[0]
    cam = pose_model.pose(0).camera(256, 256)
    ref = raycast_mask(case.vertices, case.faces, cam)
    shifted = np.roll(ref, 3, axis=1)
    assert boundary_disagreement(shifted, ref)["max_px"] >= 1.5


def test_path_length_through_a_sphere_matches_the_analytic_chord():
    import trimesh

    r = 6.0
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r)
    centre = np.array([3.0, -2.0, 5.0])
    V = sphere.vertices + centre
    cam = Camera.from_carm(20.0, 10.0, 1000.0, 750.0, 0.3, 128, 128)
    L = rasterise_path_length(V, sphere.faces, cam)
    rr, cc = np.meshgrid(np.arange(128.0), np.arange(128.0), indexing="ij")
    o, d = cam.rays(np.stack([rr.ravel(), cc.ravel()], 1))
    w = centre - o
    dist2 = (w ** 2).sum(1) - ((w * d).sum(1)) ** 2
    chord = 2 * np.sqrt(np.clip(r * r - dist2, 0, None)).reshape(128, 128)
    inside = chord > 1.0
    assert np.median(np.abs(L[inside] - chord[inside])) < 0.02
    assert abs(L.max() - 2 * r) < 0.05
    # weighting by a per-face concentration scales the length
    half = rasterise_path_length(V, sphere.faces, cam, face_weight=np.full(len(sphere.faces), 0.5))
    np.testing.assert_allclose(half[inside], 0.5 * L[inside], rtol=1e-5)


def test_one_pass_lumen_raster_gives_the_silhouette_and_the_path_length(cases, pose_model):
    """rasterise_lumen (what the XA simulator uses per frame) = rasterise_mask + rasterise_path_length,
    and its image-space front-face test agrees with the 3D normal test on every non-degenerate face."""
    from stages.render.raster import _front_faces, rasterise_lumen

    rng = np.random.default_rng(7)
    for i, case in enumerate(cases):
        cam = pose_model.sample_pair(rng)[i % 2].camera(256, 256)
        V, F = case.vertices.astype(float), case.faces
        w = rng.uniform(0.2, 1.0, len(F))
        mask, L = rasterise_lumen(V, F, cam, face_weight=w)
        np.testing.assert_array_equal(mask, rasterise_mask(V, F, cam))
        np.testing.assert_array_equal(L, rasterise_path_length(V, F, cam, face_weight=w))
        assert mask.sum() > 200 and (L[mask] > 0).mean() > 0.99 and not L[~mask].any()
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        towards = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - cam.source)
        front3d = towards < 0
        front2d = np.zeros(len(F), bool)
        front2d[_front_faces(cam.project(V)[F], cam)] = True
        clear = np.abs(towards) > 1e-6 * np.abs(towards).max()
        np.testing.assert_array_equal(front2d[clear], front3d[clear])


def test_random_warp_has_requested_rms_and_is_reproducible_from_params():
    rng = np.random.default_rng(5)
    w = random_warp(rng, 512, 512, rms_px=3.0)
    assert abs(w.rms(512, 512) - 3.0) < 1e-6
    w2 = Warp2D.from_params(w.params(), 512.0)
    pts = np.random.default_rng(1).uniform(0, 511, (50, 2))
    np.testing.assert_allclose(w2.apply(pts), w.apply(pts), atol=1e-9)
    # smooth: neighbouring pixels move almost alike
    d = w.displacement(pts) - w.displacement(pts + 1.0)
    assert np.abs(d).max() < 0.2


def test_warped_silhouette_follows_the_warp(cases, pose_model):
    case = cases[1]
    cam = pose_model.pose(3).camera(256, 256)
    V = case.vertices.astype(float)
    w = random_warp(np.random.default_rng(3), 256, 256, rms_px=4.0)
    warped = rasterise_mask(V, case.faces, cam, offset_rc=w.displacement(cam.project(V)))
    plain = rasterise_mask(V, case.faces, cam)
    # centreline nodes deep inside the lumen stay inside after warping both the mask and the points
    thick = case.radius > 1.3
    uv = w.apply(cam.project(case.nodes[thick]))
    ij = np.rint(uv).astype(int)
    assert warped[ij[:, 0], ij[:, 1]].mean() > 0.95
    assert (warped != plain).sum() > 50


def test_heart_motion_amplitudes_and_periodicity(cases):
    case = cases[0]
    m = HeartMotion.for_points(case.nodes, case.heart, radial=0.12, axial=0.12, twist_deg=8.0, t_systole=0.35,
                               rr_intervals=[1.0] * 5, resp_vector=[0, 0, -8.0])
    P = case.nodes.astype(float)
    np.testing.assert_allclose(m.apply(P, 0.0), P, atol=1e-9)
    np.testing.assert_allclose(m.apply(P, 0.999999), P, atol=1e-3)
    assert contraction(0.35, 0.35, 0.2) == pytest.approx(1.0)
    c, u = np.asarray(m.centre), np.asarray(m.long_axis)
    Q = m.apply(P, 0.35)
    rad0 = np.linalg.norm((P - c) - np.outer((P - c) @ u, u), axis=1)
    rad1 = np.linalg.norm((Q - c) - np.outer((Q - c) @ u, u), axis=1)
    np.testing.assert_allclose(rad1, 0.88 * rad0, rtol=1e-9)
    a0, a1 = (P - c) @ u, (Q - c) @ u
    span0, span1 = np.ptp(a0), np.ptp(a1)
    assert span1 == pytest.approx(0.88 * span0, rel=1e-6)
    # respiration is a pure translation
    np.testing.assert_allclose(m.apply(P, 0.0, 1.0) - P, np.tile([0, 0, -8.0], (len(P), 1)), atol=1e-9)


def test_sampled_motion_ranges():
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 30
    for s in range(20):
        m = sample_motion(pts, np.random.default_rng(s), duration=20.0)
        assert 50 <= m.heart_rate_bpm <= 100
        assert 0.10 <= m.radial <= 0.15 and 0.10 <= m.axial <= 0.15 and 5 <= m.twist_deg <= 10
        assert np.linalg.norm(m.resp_vector) <= 10.0
        ph = m.phase_at(np.linspace(0, 20, 400))
        assert ph.min() >= 0 and ph.max() < 1


def test_render_pair_is_deterministic_and_consistent(cases, pose_model):
    a = render_pair(cases[2], pose_model, np.random.default_rng(7), size=256, misalign_3d=1.0)
    b = render_pair(cases[2], pose_model, np.random.default_rng(7), size=256, misalign_3d=1.0)
    assert np.array_equal(a["mask_a"], b["mask_a"]) and np.array_equal(a["mask_b"], b["mask_b"])
    assert a["pose_a"].cluster != a["pose_b"].cluster
    assert a["mask_a"].shape == (256, 256) and a["mask_a"].sum() > 100 and a["mask_b"].sum() > 100
    assert 0.1 <= a["phase_b"] <= 0.5
    # view a is exact: the translated labels' occupied voxels project inside the silhouette
    lab = cases[2].labels
    X = lab.world_points()[lab.features["occupancy"] == 1] + a["translation"]
    rc = np.rint(a["camera_a"].project(X)).astype(int)
    ok = a["camera_a"].in_image(rc)
    assert a["mask_a"][rc[ok, 0], rc[ok, 1]].mean() > 0.97


def test_bad_inputs_give_clear_messages(cases, pose_model, tmp_path):
    from stages.render.acquire import check_visibility
    from stages.render.pairs import pose_model_from

    path = tmp_path / "case.zarr"
    cases[0].save(path)
    with pytest.raises(UserError, match="expected an artefact of kind 'autocar.pose-model'"):
        pose_model_from(path)
    with pytest.raises(UserError, match="SOD .* must be smaller than SID"):
        Camera.from_carm(0, 0, 700, 800, 0.3, 512, 512)
    with pytest.raises(UserError, match="pixel spacing must be positive"):
        Camera.from_carm(0, 0, 1000, 700, 0.0, 512, 512)
    cam = Camera.from_carm(0, 0, 1000, 700, 0.3, 512, 512)
    far = cases[0].nodes + np.array([150.0, 0, 0])
    with pytest.raises(UserError, match=r"only \d+% of the tree is inside"):
        check_visibility(far, cam, "test")
    half = cases[0].nodes.copy()
    half[: len(half) // 4] += np.array([150.0, 0, 0])
    assert 0.5 <= check_visibility(half, cam, "test") < 1.0
    with pytest.raises(UserError, match="does not fit the field of view"):
        render_pair(cases[0], pose_model, np.random.default_rng(0), size=64, translation_mm=0, jitter_px=0,
                    min_visible=1.01, max_tries=2)


def test_decimated_meshes_are_cached_by_content(cases, tmp_path, monkeypatch):
    """The cache gives back exactly what decimation gives, keyed by the mesh (not the file name)."""
    import trimesh

    from stages.render.pairs import simplified_for_rendering

    fresh = simplified_for_rendering(cases[0], max_faces=4000)
    first = simplified_for_rendering(cases[0], max_faces=4000, cache_dir=tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 1
    assert len(first.faces) <= 4000 and np.array_equal(first.faces, fresh.faces)

    def no_decimation(*args, **kwargs):
        raise AssertionError("decimated again despite the cache")

    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", no_decimation)
    again = simplified_for_rendering(cases[0], max_faces=4000, cache_dir=tmp_path / "cache")
    assert np.array_equal(again.vertices, fresh.vertices) and np.array_equal(again.faces, fresh.faces)
    assert again.case_id == cases[0].case_id and again.labels is cases[0].labels
    # another mesh or another face budget is another entry
    monkeypatch.undo()
    simplified_for_rendering(cases[1], max_faces=4000, cache_dir=tmp_path / "cache")
    simplified_for_rendering(cases[0], max_faces=3000, cache_dir=tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 3
    # a damaged entry is decimated again and rewritten
    for f in (tmp_path / "cache").glob("*.npz"):
        f.write_bytes(b"not an npz")
    redone = simplified_for_rendering(cases[0], max_faces=4000, cache_dir=tmp_path / "cache")
    assert np.array_equal(redone.faces, fresh.faces)
    assert sum(f.stat().st_size > 100 for f in (tmp_path / "cache").glob("*.npz")) == 1

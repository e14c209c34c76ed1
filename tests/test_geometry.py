"""C-arm geometry: hand-derived projections, back-projection, NumPy/torch/matrix agreement, gradients."""

import json
import math

import numpy as np
import pytest
import torch

from stages.core.errors import UserError
from stages.core.geometry import Camera, camera_from_geometry_dict, carm_camera_torch, load_geometry_json, project_points_torch

SID, SOD, SP, N = 1000.0, 750.0, 0.5, 512
C0 = (N - 1) / 2  # 255.5: image centre, pixel centres at integer indices
F = SID / SP  # focal length in pixels


def cam(alpha, beta):
    return Camera.from_carm(alpha, beta, SID, SOD, SP, N, N)


def test_ap_view_hand_derived():
    c = cam(0, 0)
    np.testing.assert_allclose(c.source, [0, 750, 0])  # source posterior
    pts = np.array([[0, 0, 0], [10, 0, 0], [0, 0, 20], [10, -250, 0]], float)
    rc = c.project(pts)
    # isocentre on the image centre; patient left (+x) to screen right; head (+z) up; magnification SID/depth
    np.testing.assert_allclose(rc[0], [C0, C0], atol=1e-9)
    np.testing.assert_allclose(rc[1], [C0, C0 + F * 10 / 750], atol=1e-9)
    np.testing.assert_allclose(rc[2], [C0 - F * 20 / 750, C0], atol=1e-9)
    np.testing.assert_allclose(rc[3], [C0, C0 + 20.0], atol=1e-9)  # on the detector plane: magnification 1
    assert c.isocentre_spacing == pytest.approx(SP * SOD / SID)


def test_lao90_view_spine_on_the_right():
    c = cam(90, 0)
    np.testing.assert_allclose(c.source, [-750, 0, 0], atol=1e-9)  # source at the patient's right
    rc = c.project(np.array([[0, 10, 0], [250, 10, 0], [0, 0, 10]], float))
    np.testing.assert_allclose(rc[0], [C0, C0 + F * 10 / 750], atol=1e-9)  # posterior (spine) → screen right
    np.testing.assert_allclose(rc[1], [C0, C0 + 20.0], atol=1e-9)
    np.testing.assert_allclose(rc[2], [C0 - F * 10 / 750, C0], atol=1e-9)


def test_rao30_view():
    c = cam(-30, 0)
    a = math.radians(-30)
    rc = c.project(np.array([[10, 0, 0]], float))[0]
    depth = SOD + 10 * math.sin(a)  # d·X with d = (sin α, −cos α, 0)
    np.testing.assert_allclose(rc, [C0, C0 + F * 10 * math.cos(a) / depth], atol=1e-9)


def test_cranial30_view():
    c = cam(0, 30)
    b = math.radians(30)
    rc = c.project(np.array([[0, 0, 10], [10, 0, 0]], float))
    # superior point: depth 750 + 10 sin β, row offset −10 cos β (head up)
    np.testing.assert_allclose(rc[0], [C0 - F * 10 * math.cos(b) / (SOD + 10 * math.sin(b)), C0], atol=1e-9)
    np.testing.assert_allclose(rc[1], [C0, C0 + F * 10 / SOD], atol=1e-9)


def test_rays_project_back_onto_their_pixels():
    rng = np.random.default_rng(1)
    c = Camera.from_carm(37.0, -21.0, 1100, 780, (0.3, 0.32), 480, 640)
    pix = rng.uniform([0, 0], [479, 639], size=(200, 2))
    origins, dirs = c.rays(pix)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(origins, np.broadcast_to(c.source, origins.shape))
    for t in (300.0, 780.0, 1050.0):
        rc = c.project(origins + t * dirs)
        assert np.abs(rc - pix).max() < 1e-6


def test_numpy_torch_matrix_agree():
    rng = np.random.default_rng(2)
    pts = rng.normal(0, 50, (500, 3))
    for alpha, beta in [(0, 0), (45, 25), (-30, -25), (90, 0), (12.3, 41.0)]:
        c = Camera.from_carm(alpha, beta, 1050, 760, (0.28, 0.29), 512, 500)
        rc_np = c.project(pts)
        rc_t = c.project_torch(torch.tensor(pts)).numpy()
        h = np.c_[pts, np.ones(len(pts))] @ c.matrix.T
        rc_m = np.stack([h[:, 1] / h[:, 2], h[:, 0] / h[:, 2]], axis=1)
        K, R, S = carm_camera_torch(*(torch.tensor(float(v), dtype=torch.float64) for v in (alpha, beta, 1050, 760, 0.28, 0.29)), 512, 500)
        rc_tp = project_points_torch(torch.tensor(pts), K, R, S).numpy()
        for other in (rc_t, rc_m, rc_tp):
            assert np.abs(rc_np - other).max() < 1e-6


def test_matrix_camera_roundtrip_any_scale():
    c = Camera.from_carm(-27.3, 18.0, 900, 720, 0.39, 512, 512)
    pts = np.random.default_rng(3).normal(0, 40, (100, 3))
    for scale in (1.0, 3.7, -0.01):
        m = Camera.from_matrix(c.matrix * scale, 512, 512)
        assert np.abs(m.project(pts) - c.project(pts)).max() < 1e-6
        np.testing.assert_allclose(m.source, c.source, atol=1e-6)
        assert m.isocentre_spacing == pytest.approx(c.isocentre_spacing)


def test_torch_gradients_gradcheck():
    c = Camera.from_carm(30, 20, 1000, 750, 0.3, 256, 256)
    pts = torch.randn(6, 3, dtype=torch.float64) * 30
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: c.project_torch(p), (pts,))
    params = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (30.0, 20.0, 1000.0, 750.0, 0.3, 0.31)]

    def f(*p):
        K, R, S = carm_camera_torch(*p, 256, 256)
        return project_points_torch(pts.detach(), K, R, S)

    assert torch.autograd.gradcheck(f, tuple(params))


def test_geometry_json_forms(tmp_path):
    dicom_style = {"PositionerPrimaryAngle": 30, "PositionerSecondaryAngle": -20, "DistanceSourceToDetector": 1000,
                   "DistanceSourceToPatient": 750, "ImagerPixelSpacing": [0.3, 0.3], "Rows": 512, "Columns": 512}
    p = tmp_path / "g.json"
    p.write_text(json.dumps(dicom_style))
    c = load_geometry_json(p)
    ref = Camera.from_carm(30, -20, 1000, 750, 0.3, 512, 512)
    pts = np.random.default_rng(4).normal(0, 30, (20, 3))
    assert np.abs(c.project(pts) - ref.project(pts)).max() < 1e-9
    m = camera_from_geometry_dict({"matrix": ref.matrix.tolist(), "rows": 512, "cols": 512})
    assert np.abs(m.project(pts) - ref.project(pts)).max() < 1e-6
    back = Camera.from_dict(ref.to_dict())
    assert np.abs(back.project(pts) - ref.project(pts)).max() < 1e-9 and back.carm == ref.carm


@pytest.mark.parametrize("bad, fragment", [
    ({"PositionerPrimaryAngle": 30, "Rows": 512, "Columns": 512}, "missing geometry field"),
    ({"alpha": 0, "beta": 0, "sid": 700, "sod": 750, "spacing": 0.3, "rows": 512, "cols": 512}, "SOD"),
    ({"alpha": 0, "beta": 0, "sid": 1000, "sod": 750, "spacing": 0.0, "rows": 512, "cols": 512}, "spacing"),
    ({"matrix": [[1, 0, 0, 0]] * 3, "rows": 10, "cols": 10}, "singular"),
])
def test_geometry_json_errors(tmp_path, bad, fragment):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(bad))
    with pytest.raises(UserError) as exc:
        load_geometry_json(p)
    assert fragment in str(exc.value)


def test_resampled_camera_maps_pixel_centres_consistently():
    # a view sampled 2× finer: a world point's pixel x becomes (x + ½)·2 − ½, the isocentre pixel halves
    cam = Camera.from_carm(30.0, 20.0, 1000.0, 750.0, 0.8, 256, 256)
    fine = cam.resampled(2)
    pts = np.random.default_rng(3).normal(size=(20, 3)) * 30.0
    assert np.allclose((cam.project(pts) + 0.5) * 2 - 0.5, fine.project(pts), atol=1e-9)
    assert (fine.rows, fine.cols) == (512, 512)
    assert fine.isocentre_spacing == pytest.approx(cam.isocentre_spacing / 2)
    assert fine.carm["spacing"] == [0.4, 0.4]

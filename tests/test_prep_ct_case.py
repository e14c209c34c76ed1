"""PreparedCase storage and a procedural case prepared end to end against its analytic truth."""

from __future__ import annotations

import numpy as np
import pytest

from stages.core.errors import UserError
from stages.core.prepared_case import CaseTruth, PreparedCase, find_cases
from stages.core.voxels import SparseVoxels


def _tiny_case():
    lab = SparseVoxels(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]]), 0.5, np.array([1.0, 2.0, 3.0]),
                       {"occupancy": np.array([1, 1, 0], np.uint8), "centreness": np.array([1, .5, 0], np.float32)})
    truth = CaseTruth(np.zeros((3, 3)), [1, 1, 0.8], [0, 0, 1], [-1, 0], ["RCA", "PDA"])
    return PreparedCase("c7", "right", np.eye(3), [[0, 1, 2]], np.zeros((2, 3)), [1.5, 1.2], [[0, 1]], lab,
                        source={"synthetic": True, "seed": 7}, heart={"centre": [1, 2, 3], "long_axis": [0.6, -0.6, -0.53]},
                        stenoses=[{"branch": "RCA", "diameter_reduction": 0.5}], truth=truth)


def test_round_trip(tmp_path):
    c = _tiny_case()
    c.save(tmp_path / "c7_right.zarr")
    d = PreparedCase.load(tmp_path / "c7_right.zarr")
    assert d.case_id == "c7" and d.side == "right" and d.source["seed"] == 7
    np.testing.assert_array_equal(d.faces, c.faces)
    np.testing.assert_array_equal(d.labels.coords, c.labels.coords)
    np.testing.assert_allclose(d.labels.origin, [1, 2, 3])
    assert d.labels.features["occupancy"].dtype == np.uint8
    assert d.truth.names == ["RCA", "PDA"] and d.truth.parent.tolist() == [-1, 0]
    assert d.heart["long_axis"] == pytest.approx([0.6, -0.6, -0.53])
    assert d.stenoses[0]["branch"] == "RCA"
    assert d.graph().number_of_edges() == 1
    assert find_cases(tmp_path) == [tmp_path / "c7_right.zarr"]


def test_wrong_kind_is_a_user_error(tmp_path):
    from stages.core.artefacts import write_zarr

    with write_zarr(tmp_path / "x.zarr", kind="autocar.pose-model", schema_version=1, stage="t") as g:
        g.attrs.update({"a": 1})
    with pytest.raises(UserError, match="prepared-case"):
        PreparedCase.load(tmp_path / "x.zarr")


@pytest.mark.slow
def test_synthetic_case_meets_the_acceptance_figures(tmp_path):
    """One procedural case through the full label-volume path, both trees, measured against the truth."""
    from stages.prep_ct import PrepParams, prepare_synthetic
    from stages.prep_ct.accuracy import evaluate_case

    paths = prepare_synthetic(3, tmp_path, PrepParams())
    assert [p.name for p in paths] == ["case_0003_left.zarr", "case_0003_right.zarr"]
    assert (tmp_path / "case_0003_left.png").exists()
    for p in paths:
        case = PreparedCase.load(p)
        assert case.heart and case.truth is not None and case.source["seed"] == 3
        assert case.mesh().is_watertight
        e = evaluate_case(case)
        assert e["surface_mean"] <= 0.1 and e["surface_p95"] <= 0.25, e
        assert e["cl_pred_to_truth_mean"] <= 0.2 and e["cl_truth_to_pred_mean"] <= 0.2, e
        assert e["cl_pred_to_truth_p95"] <= 0.5 and e["cl_truth_to_pred_p95"] <= 0.5, e
        assert e["radius_mae"] <= 0.15, e
        assert e["bifurcations"] == e["bifurcations_truth"], e

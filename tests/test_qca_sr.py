"""QCA as a DICOM Structured Report (qca_sr.dcm): read back with pydicom and highdicom, its figures equal
qca.json's, it references the source runs, and runs without DICOM UIDs get none, with a reason."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stages.anatomy import generate
from stages.graph.io import write_vascular_graphs
from stages.graph.optimise import TrackedGraphs
from stages.qca.truth import truth_graph

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

EXAMPLES = Path(__file__).parents[1] / "examples"
RUNS = [EXAMPLES / "run_a.dcm", EXAMPLES / "run_b.dcm"]


@pytest.fixture(scope="module")
def qca_folder(tmp_path_factory):
    from stages.qca import qca_for_reconstruction
    from stages.qca.analysis import QCAParams

    g, _, _ = truth_graph(generate(1000003).tree("left"))
    rec = tmp_path_factory.mktemp("rec")
    write_vascular_graphs(rec / "graphs.zarr", TrackedGraphs(["00"], [g], [None], np.zeros(len(g), np.int64), []),
                          case_id="test")
    doc = qca_for_reconstruction(rec, params=QCAParams(), plots=False, views=False)
    return rec, json.loads((rec / "qca.json").read_text()), doc


def _values(group) -> dict:
    out = {}
    for m in group.get_measurements():
        key = m.name.meaning + (f" ({m.derivation.meaning})" if m.derivation is not None else "")
        out[key] = (float(m.value), m.unit.value)
    return out


def test_sr_of_a_folder_without_recorded_runs_is_not_written(qca_folder):
    rec, on_disk, doc = qca_folder
    assert doc["sr"]["file"] is None and "not recorded" in doc["sr"]["reason"]
    assert not (rec / "qca_sr.dcm").exists()


def test_sr_values_and_references_equal_qca_json(qca_folder):
    from stages.qca.sr import CODES, mean_diameter, write_qca_sr

    rec, doc, _ = qca_folder
    assert write_qca_sr(rec, doc, sources=RUNS) == {"file": "qca_sr.dcm"}
    path = rec / "qca_sr.dcm"
    ds = pydicom.dcmread(path)
    assert ds.Modality == "SR" and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.88.34"  # Comprehensive 3D SR
    assert ds.ContentTemplateSequence[0].TemplateIdentifier == "1500"
    sources = [pydicom.dcmread(p, stop_before_pixels=True) for p in RUNS]
    assert ds.StudyInstanceUID == sources[0].StudyInstanceUID
    referenced = {(s.SeriesInstanceUID, i.ReferencedSOPInstanceUID)
                  for st in ds.CurrentRequestedProcedureEvidenceSequence for s in st.ReferencedSeriesSequence
                  for i in s.ReferencedSOPSequence}
    assert {(s.SeriesInstanceUID, s.SOPInstanceUID) for s in sources} <= referenced

    groups = hd.sr.srread(path).content.get_image_measurement_groups()
    vessels = [g for g in groups if g.finding_type.value == CODES["coronary_artery"][0]]
    lesions = [g for g in groups if g.finding_type.value == CODES["stenosis"][0]]
    assert len(vessels) == len(doc["vessels"])
    assert len(lesions) == sum(len(vd["lesions"]) for vd in doc["vessels"]) > 0
    by_name = {g.tracking_identifier: g for g in groups}
    for vd in doc["vessels"]:
        v = _values(by_name[f"{vd['name']} ({vd['id']})"])
        assert v["Length"] == pytest.approx((vd["length_mm"], "mm"), abs=1e-3)
        assert v["Vessel lumen diameter (Mean)"][0] == pytest.approx(mean_diameter(vd), abs=1e-3)
        assert v["Vessel lumen diameter (Minimum)"][0] == pytest.approx(vd["min_diameter_mm"], abs=1e-3)
        for les in vd["lesions"]:
            v = _values(by_name[f"lesion {les['id']} in {vd['name']}"])
            assert v["Lumen Diameter Stenosis"] == pytest.approx((les["ds_percent"], "%"), abs=1e-3)
            assert v["Vessel lumen diameter (Minimum)"][0] == pytest.approx(les["mld_mm"], abs=1e-3)
            assert v["Reference lumen diameter"][0] == pytest.approx(les["reference_mm"], abs=1e-3)
            assert v["Stenotic Lesion Length"][0] == pytest.approx(les["length_mm"], abs=1e-3)
            assert v["Distance from the vessel origin along its centreline"][0] == pytest.approx(les["position_mm"], abs=1e-3)
    lad = by_name[next(f"{vd['name']} ({vd['id']})" for vd in doc["vessels"] if vd["name"] == "LAD")]
    assert lad.finding_sites[0].value.CodeValue == "59438005"  # SNOMED CT: left anterior descending coronary artery
    # the same inputs give the same UIDs
    first = ds.SOPInstanceUID
    write_qca_sr(rec, doc, sources=RUNS)
    assert pydicom.dcmread(path).SOPInstanceUID == first


def test_frames_runs_get_no_sr_and_a_reason(qca_folder, tmp_path):
    from stages.qca.sr import write_qca_sr

    rec, doc, _ = qca_folder
    (rec / "qca_sr.dcm").write_bytes(b"stale")
    frames = tmp_path / "frames_a"
    frames.mkdir()
    got = write_qca_sr(rec, doc, sources=[frames, RUNS[1]])
    assert got["file"] is None and "no DICOM UIDs" in got["reason"]
    assert not (rec / "qca_sr.dcm").exists()  # a stale SR does not outlive its figures

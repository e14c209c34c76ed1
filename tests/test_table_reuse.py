"""The table scripts reuse committed per-case results only when they were computed from the same inputs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import table1  # noqa: E402
import table2  # noqa: E402


def _rows(cases):
    return [{"case": c, "coverage": 0.5 + i / 10} for i, c in enumerate(cases)]


def test_table1_reuses_a_committed_row_only_under_its_cache_key(tmp_path):
    cache, docs = tmp_path / "cache", tmp_path / "table1"
    docs.mkdir()
    (docs / "hull.json").write_text(json.dumps({"rows": _rows("abcde"), "parameters": {"cache_key": "k1"}}))
    assert [r["case"] for r in table1.cached_rows(cache, "hull", "k1", 3, docs)] == ["a", "b", "c"]
    assert table1.cached_rows(cache, "hull", "k2", 3, docs) is None  # other weights or data
    assert table1.cached_rows(cache, "hull", "k1", 6, docs) is None  # fewer pairs than asked for
    assert table1.cached_rows(cache, "hull", "k1", 3) is None  # without the docs fallback
    cache.mkdir()  # the run cache wins over the committed document
    (cache / "hull-k1.json").write_text(json.dumps({"rows": _rows("xyz"), "key": "k1"}))
    assert [r["case"] for r in table1.cached_rows(cache, "hull", "k1", 2, docs)] == ["x", "y"]


def _write_row(doc_dir: Path, name: str, inputs: str, cases, refused=(), points=60):
    doc_dir.mkdir(exist_ok=True)
    (doc_dir / f"{name}.json").write_text(json.dumps({
        "rows": _rows(cases), "refused": [{"case": c, "reason": "too close"} for c in refused],
        "inputs": inputs, "parameters": {"points": points}}))
    (doc_dir / f"{name}-nograph.json").write_text(json.dumps({"rows": _rows(cases)[:1]}))


def test_table2_reuses_a_committed_row_only_from_the_same_inputs(tmp_path):
    docs = tmp_path / "table2"
    fp = table2.inputs_fingerprint("visual-hull", None)
    _write_row(docs, "VH", fp, ["c1", "c2"], refused=["c3"])
    part = table2.reused_row(docs, "VH", "visual-hull", None, {"c1", "c2", "c3"}, 60, None)
    assert [r["case"] for r in part["results"]["VH"]] == ["c1", "c2"]
    assert len(part["results"]["VH-nograph"]) == 1 and part["refused"][0]["case"] == "c3"
    with pytest.raises(ValueError, match="other cases"):
        table2.reused_row(docs, "VH", "visual-hull", None, {"c1", "c2"}, 60, None)
    with pytest.raises(ValueError, match="other cases"):
        table2.reused_row(docs, "VH", "visual-hull", None, {"c1", "c2", "c3"}, 30, None)
    _write_row(docs, "VH", "0123456789abcdef", ["c1", "c2"], refused=["c3"])
    with pytest.raises(ValueError, match="other inputs"):
        table2.reused_row(docs, "VH", "visual-hull", None, {"c1", "c2", "c3"}, 60, None)
    with pytest.raises(ValueError, match="missing"):
        table2.reused_row(docs, "L2", "dense", None, {"c1"}, 60, None)


def test_table2_fingerprint_follows_the_weights(tmp_path):
    w = tmp_path / "w.pt"
    w.write_bytes(b"one")
    first = table2.inputs_fingerprint("sbp", w)
    w.write_bytes(b"two")
    assert table2.inputs_fingerprint("sbp", w) != first
    assert table2.inputs_fingerprint("dense", w) != table2.inputs_fingerprint("sbp", w)


def test_table2_reuses_a_phantom_row_only_under_its_key(tmp_path):
    docs, phantom = tmp_path / "table2", tmp_path / "phantom"
    phantom.mkdir()
    for i in range(3):
        (phantom / f"IM{i}.dcm").write_bytes(bytes([i]) * 10)
    _write_row(docs, "VH", table2.inputs_fingerprint("visual-hull", None), ["c1"])
    held = {"configuration": "Visual hull", "name": "VH", "rows": [{"pair": "IM0+IM1"}], "s_per_pair": 1.0}
    (docs / "heldout_VH.json").write_text(json.dumps({**held, "key": "stale"}))
    # a stale phantom part leaves the data-re part reusable; only the phantom part is to be recomputed
    stale = table2.reused_row(docs, "VH", "visual-hull", None, {"c1"}, 60, phantom)
    assert stale["heldout"] is None and stale["results"]["VH"]
    key = table2.heldout_key("visual-hull", None, phantom)
    (docs / "heldout_VH.json").write_text(json.dumps({**held, "key": key}))
    part = table2.reused_row(docs, "VH", "visual-hull", None, {"c1"}, 60, phantom)
    assert part["heldout"] == {"name": "VH", "rows": [{"pair": "IM0+IM1"}], "s_per_pair": 1.0}


class _Inline:
    """A stand-in for the worker pool: runs each job when submitted."""

    def __init__(self, *_):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, job):
        from concurrent.futures import Future

        f = Future()
        f.set_result(fn(job))
        return f


def test_table2_default_row_shares_its_methods_reconstructions_and_writes_its_own_json(tmp_path, monkeypatch):
    """The default row is the default method's row's very reconstructions (computed once, under that row): its
    per-case JSON, refusals and phantom rows are that row's, and the reading does not compare a row with itself
    (it crashed at the end of a full run)."""
    import stages.evaluate.end_to_end as e2e
    import stages.evaluate.heldout as heldout

    data, phantom = tmp_path / "re", tmp_path / "phantom"
    for c in ("case_1", "case_2", "case_3"):
        (data / c / "truth.zarr").mkdir(parents=True)
    phantom.mkdir()
    for i in range(3):
        (phantom / f"IM{i + 1}.dcm").write_bytes(bytes([i]) * 10)
    computed = []

    def fake_case(job):
        name, method, weights, case, dst, points, fresh = job
        computed.append((name, Path(case).name))
        if Path(case).name == "case_3":
            return {"name": name, "case": "case_3", "refused": "runs 7.8° apart"}
        # VH covers more and places worse, CO is below L8 on all three: L8 is then best on two metrics of three
        coverage, epe, accuracy = {"VH": (0.95, 5.0, 0.5), "L8": (0.9, 2.0, 0.8), "CO": (0.85, 3.0, 0.7)}[name]
        row = {"case": Path(case).name, "wall_s": 1.0, "seconds": 1.0, "coverage": coverage,
               "epe_mm": epe, "accuracy": accuracy,
               "centreline_error_mm": 1.0, "centreline_pred_to_truth_mm": 1.0, "centreline_truth_to_pred_mm": 1.0,
               "topology_agreement": 1.0, "bifurcations": 3, "gt_bifurcations": 3}
        return {"name": name, "case": Path(case).name, "cached": False, "rows": {"graph": row, "nograph": dict(row)}}

    def fake_phantom(job):
        rows = [{"pair": p, "heldout": h, "pose": "nominal", "coverage": c, "distance_mm": 3.0, "distance_median_mm": 2.0,
                 "status": "ok"} for p, h, c in (("IM1+IM2", "IM3", 0.5), ("IM1+IM3", "IM2", 0.7))]
        return {"name": job[0], "rows": rows, "s_per_pair": 1.0, "views": ["IM1", "IM2", "IM3"], "pairs": [[0, 1], [0, 2]]}

    monkeypatch.setattr(e2e, "run_case", fake_case)
    monkeypatch.setattr(e2e, "process_pool", _Inline)
    monkeypatch.setattr(heldout, "method_job", fake_phantom)
    doc = tmp_path / "docs" / "TABLE2.md"
    assert table2.main(["--data", str(data), "--phantom", str(phantom), "--only", "VH,L8,CO,default", "--jobs", "1",
                        "--cache", str(tmp_path / "cache"), "--doc", str(doc)]) in (0, None)
    alias = table2.resolve_default()[2]
    assert alias in ("L8", "CO")
    assert {n for n, _ in computed} == {"VH", "L8", "CO"}  # the default row's reconstructions are its row's, once
    out = json.loads((doc.parent / "table2" / "default.json").read_text())
    assert [r["case"] for r in out["rows"]] == ["case_1", "case_2"] and out["refused"][0]["case"] == "case_3"
    same = json.loads((doc.parent / "table2" / f"{alias}.json").read_text())
    assert out["inputs"] == same["inputs"] and out["rows"] == same["rows"]
    assert (doc.parent / "table2" / "heldout_default.json").exists()
    text = doc.read_text()
    assert "reproduces in part" in text and "every other configuration is below L8" in text  # not L8 against itself
    # a rerun that takes every row from docs/ keeps the default row: it follows its row when that row is reused
    # too (it used to vanish from TABLE2.md, since the alias was resolved before the reused rows were read)
    computed.clear()
    assert table2.main(["--data", str(data), "--phantom", str(phantom), "--only", "VH,L8,CO,default", "--jobs", "1",
                        "--cache", str(tmp_path / "cache2"), "--doc", str(doc), "--reuse-docs"]) in (0, None)
    assert computed == []
    text = doc.read_text()
    default_rows = [ln for ln in text.splitlines() if ln.startswith("| `autocar reconstruct`'s default 3D method")]
    assert len(default_rows) == 2  # data-re and the phantom
    assert json.loads((doc.parent / "table2" / "default.json").read_text())["rows"] == same["rows"]
    # only a phantom part gone stale (its key changed): the data-re rows are reused, the phantom rows recomputed
    phantom_jobs = []
    monkeypatch.setattr(heldout, "method_job", lambda job: phantom_jobs.append(job[0]) or fake_phantom(job))
    monkeypatch.setattr(table2, "HELDOUT_VERSION", table2.HELDOUT_VERSION + 1)
    assert table2.main(["--data", str(data), "--phantom", str(phantom), "--only", "VH,L8,CO,default", "--jobs", "1",
                        "--cache", str(tmp_path / "cache3"), "--doc", str(doc), "--reuse-docs"]) in (0, None)
    assert computed == [] and sorted(phantom_jobs) == ["CO", "L8", "VH"]
    assert table2.heldout_key("visual-hull", None, phantom) == json.loads(
        (doc.parent / "table2" / "heldout_VH.json").read_text())["key"]

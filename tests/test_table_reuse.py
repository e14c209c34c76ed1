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
    with pytest.raises(ValueError, match="heldout_VH.json"):
        table2.reused_row(docs, "VH", "visual-hull", None, {"c1"}, 60, phantom)
    key = table2.heldout_key("visual-hull", None, phantom)
    (docs / "heldout_VH.json").write_text(json.dumps({**held, "key": key}))
    part = table2.reused_row(docs, "VH", "visual-hull", None, {"c1"}, 60, phantom)
    assert part["heldout"] == {"name": "VH", "rows": [{"pair": "IM0+IM1"}], "s_per_pair": 1.0}

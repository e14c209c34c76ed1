"""Procedural coronary anatomy: determinism, plausible sizes, Murray's law, stenoses, label volume."""

from __future__ import annotations

import numpy as np
import pytest

from stages.anatomy import R_MIN, R_MIN_STENOSIS, _arclength, generate

SEEDS = list(range(12))


@pytest.fixture(scope="module")
def anatomies():
    return {s: generate(s) for s in SEEDS}


def test_same_seed_same_anatomy():
    a, b = generate(11), generate(11)
    for ta, tb in ((a.left, b.left), (a.right, b.right)):
        assert [x.name for x in ta.branches] == [x.name for x in tb.branches]
        for x, y in zip(ta.branches, tb.branches):
            np.testing.assert_array_equal(x.points, y.points)
            np.testing.assert_array_equal(x.radius, y.radius)
    assert not np.allclose(generate(12).heart.u, a.heart.u)


def test_heart_placement(anatomies):
    for a in anatomies.values():
        h = a.heart
        assert np.linalg.norm(h.centre) < 20
        u = h.u
        assert abs(np.linalg.norm(u) - 1) < 1e-9
        assert u[0] > 0.3 and u[1] < -0.3 and u[2] < -0.1  # base → apex: left, anterior, inferior
        lo, hi = a.bounds()
        assert np.all(hi - lo < 125)  # both trees inside a ~110–120 mm field of view
        d = h.to_dict()
        assert set(d) >= {"centre", "long_axis"}


def test_branch_sizes(anatomies):
    for a in anatomies.values():
        L, R = a.left, a.right
        lm = L.branches[L.index("LM")]
        assert 5 <= lm.length <= 15.5 and 4.0 <= 2 * lm.radius[0] <= 5.0
        lad = L.branches[L.index("LAD")]
        assert 95 <= lad.length <= 141 and 3.0 <= 2 * lad.radius[0] <= 4.0
        lcx = L.branches[L.index("LCx")]
        assert lcx.length >= 55 and (a.dominance == "left" or lcx.length <= 91)
        names = [b.name for b in L.branches]
        assert 1 <= sum(n.startswith("D") for n in names) <= 3
        assert 1 <= sum(n.startswith("OM") for n in names) <= 3
        assert sum(n.startswith("S") for n in names) >= 1
        rca = R.branches[R.index("RCA")]
        assert 3.5 <= 2 * rca.radius[0] <= 4.5 and rca.length >= 60
        rnames = [b.name for b in R.branches]
        assert "conus" in rnames and any(n.startswith("AM") for n in rnames)
        assert ("PDA" in rnames) == (a.dominance != "left")
        for t in (L, R):
            for b in t.branches:
                assert b.radius.min() >= R_MIN_STENOSIS - 1e-9
                in_sten = any(s["branch"] == b.name for s in t.stenoses)
                if not in_sten:
                    assert b.radius.min() >= R_MIN - 1e-9


def test_murrays_law_at_branch_points(anatomies):
    checked = 0
    for a in anatomies.values():
        for t in (a.left, a.right):
            for child in t.branches:
                if child.parent < 0:
                    continue
                par = t.branches[child.parent]
                if child.attach >= len(par.points) - 1:  # the left-main split: all children at its end
                    kids = [c for c in t.branches if c.parent == child.parent]
                    lhs = par.radius[-1] ** 3
                    rhs = sum(c.radius[0] ** 3 for c in kids)
                else:
                    s = _arclength(par.points)
                    before = np.searchsorted(s, s[child.attach] - 0.5)
                    after = np.searchsorted(s, s[child.attach] + 2.5)
                    if any(s["branch"] == par.name for s in t.stenoses):
                        continue
                    lhs = par.radius[before] ** 3
                    rhs = par.radius[min(after, len(s) - 1)] ** 3 + child.radius[0] ** 3
                assert abs(lhs - rhs) / lhs < 0.2, (child.name, lhs, rhs)
                checked += 1
    assert checked > 30


def test_stenoses(anatomies):
    seen = 0
    for a in anatomies.values():
        for t in (a.left, a.right):
            assert len(t.stenoses) <= 3
            for s in t.stenoses:
                seen += 1
                assert 3 <= s["length_mm"] <= 15
                assert 0.25 <= s["requested_reduction"] <= 0.9
                assert 0.2 <= s["diameter_reduction"] <= s["requested_reduction"] + 1e-9
                b = t.branches[t.index(s["branch"])]
                d = _arclength(b.points)
                k = np.argmin(np.abs(d - s["position_mm"]))
                assert abs(2 * b.radius[k] - s["reference_diameter_mm"] * (1 - s["diameter_reduction"])) < 0.05
    assert seen > 0


def test_trees_are_separate_and_bifurcations_counted(anatomies):
    from scipy.spatial import cKDTree

    for a in anatomies.values():
        pl, rl = a.left.samples(1.0)
        pr, rr = a.right.samples(1.0)
        d, i = cKDTree(pr).query(pl)
        assert (d - rl - rr[i]).min() >= 3.0
        n_children = len(a.left.branches) - 1
        # the LM split into n children counts n − 1, every other child 1
        ends = sum(1 for b in a.left.branches if b.parent == 0)
        assert ends >= 2 and a.left.bifurcation_count() == n_children - 1
        assert a.right.bifurcation_count() == len(a.right.branches) - 1


def test_label_volume(anatomies):
    a = anatomies[2]
    vol = a.label_volume(spacing=(0.4, 0.4, 0.5))
    np.testing.assert_allclose(vol.spacing, [0.4, 0.4, 0.5])
    assert set(np.unique(vol.data)) == {0, 1, 2}
    # every truth centreline point lies in a voxel of its own tree's label
    for value, tree in ((1, a.left), (2, a.right)):
        pts, rad = tree.samples(2.0)
        idx = np.rint((pts - vol.affine[:3, 3]) / vol.spacing).astype(int)
        assert np.mean(vol.data[tuple(idx.T)] == value) > 0.99
    # voxel count ≈ analytic volume (union of balls), within 10 %
    from stages.anatomy import Tree  # noqa: F401

    n1 = np.count_nonzero(vol.data == 1) * np.prod(vol.spacing)
    length_vol = sum(np.sum(np.pi * b.radius[:-1] ** 2 * np.diff(_arclength(b.points))) for b in a.left.branches)
    assert 0.8 < n1 / length_vol < 1.1
    full = a.label_volume(spacing=(0.4, 0.4, 0.4), shape=(300, 300, 260))
    assert full.data.shape == (300, 300, 260)
    assert np.count_nonzero(full.data == 1) == pytest.approx(np.count_nonzero(vol.data == 1) * 0.5 / 0.4, rel=0.05)

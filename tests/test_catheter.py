"""The 2D catheter rule (stages.core.catheter.catheter_lines): a straight piece entering the image is a
catheter, also when a vessel crossing it near the edge cuts its skeleton into pieces no one of which both is
long enough and reaches the edge; straight vessel pieces inside the image are not."""

from __future__ import annotations

import numpy as np

from stages.core.catheter import MAX_LINE_GAP_PX, along_lines, catheter_lines

SHAPE = (512, 512)


def _segment(r0, c0, r1, c1):
    """Pixels every 1 px from (r0, c0) to (r1, c1)."""
    n = int(np.ceil(np.hypot(r1 - r0, c1 - c0))) + 1
    return np.stack([np.linspace(r0, r1, n), np.linspace(c0, c1, n)], 1)


def test_a_catheter_cut_near_the_edge_is_still_found():
    # from the top edge, cut at row 70 by a crossing vessel: 66 px reach the edge, 220 px do not
    top, rest = _segment(5, 200, 70, 203), _segment(78, 203.4, 298, 213.6)
    vessel = _segment(74, 120, 140, 330)
    lines = catheter_lines([top, rest, vessel], SHAPE)
    assert len(lines) == 1
    assert along_lines(top, lines) and along_lines(rest, lines) and not along_lines(vessel, lines)
    # each piece alone fails the single-piece rule: too short, or not entering the image
    assert catheter_lines([top], SHAPE) == [] and catheter_lines([rest], SHAPE) == []


def test_straight_pieces_inside_the_image_or_far_apart_are_not_a_catheter():
    inside = [_segment(150, 100, 210, 160), _segment(218, 168, 300, 250)]
    assert catheter_lines(inside, SHAPE) == []
    gap = MAX_LINE_GAP_PX + 15
    apart = [_segment(5, 300, 70, 300), _segment(70 + gap, 300, 200 + gap, 300)]
    assert catheter_lines(apart, SHAPE) == []

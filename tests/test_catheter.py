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


def _disc_path(shape, points, radius) -> np.ndarray:
    """A mask of discs of ``radius`` px along ``points`` (K×2, row/col)."""
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    out = np.zeros(shape, bool)
    for r, c in points:
        out |= (rr - r) ** 2 + (cc - c) ** 2 <= radius ** 2
    return out


def test_a_curved_catheter_seen_before_the_contrast_leaves_the_key_frame_and_the_vessels_stay():
    """A curved catheter from the top edge, moving with the heart, is the only tube of a run's first six frames;
    then a vessel continuing its tip and one crossing it fill. In a filled frame the catheter goes, the vessels
    (the crossing included) stay whole."""
    from scipy import ndimage

    from stages.core.catheter import precontrast_catheter, precontrast_frames

    shape = (256, 256)
    t = np.linspace(0.0, 1.0, 200)
    catheter = np.c_[100 * t, 60 + 60 * t ** 2]  # from the top edge, bending, tip at (100, 120)
    tip_vessel = np.c_[np.linspace(100, 170, 100), np.linspace(120, 190, 100)]  # continues the tip
    crossing = np.c_[np.linspace(40, 62, 200), np.linspace(10, 210, 200)]  # crosses the catheter near (46, 73)
    vessels = _disc_path(shape, tip_vessel, 3.0) | _disc_path(shape, crossing, 2.0)
    tube = _disc_path(shape, catheter, 2.5)
    moves = [(int(round(3 * np.sin(f))), int(round(2 * np.cos(f)))) for f in range(16)]  # heart and breathing
    frames = np.stack([np.roll(tube, m, (0, 1)) | (vessels if f >= 6 else False) for f, m in enumerate(moves)])
    before = precontrast_frames(frames)
    assert before is not None and len(before) == 5  # the sixth may already fill at the ostium: left out

    key = 12
    gone = precontrast_catheter(frames[key], before)
    moved_tube = np.roll(tube, moves[key], (0, 1))
    away = moved_tube & ~ndimage.binary_dilation(vessels, iterations=8)
    assert gone[away].mean() > 0.9
    # the vessel's pixels stay, but for those just past the tip, where it continues the catheter's course
    past_tip = _disc_path(shape, tip_vessel[:10], 3.0)
    assert gone[vessels & ~moved_tube & ~past_tip].mean() < 0.005
    kept = frames[key] & ~gone
    assert ndimage.label(kept & ndimage.binary_dilation(_disc_path(shape, crossing, 2.0), iterations=1))[1] == 1
    assert not gone[_disc_path(shape, tip_vessel[10:], 3.0)].any()


def test_runs_without_frames_before_the_contrast_keep_their_masks():
    from stages.core.catheter import precontrast_catheter, precontrast_frames

    shape = (128, 128)
    tree = _disc_path(shape, np.c_[np.linspace(10, 120, 60), np.linspace(20, 100, 60)], 3.0)
    filled = np.stack([tree] * 10)  # a phantom filled throughout, or a run that starts after the injection
    assert precontrast_frames(filled) is None
    empty_start = np.stack([np.zeros(shape, bool)] * 4 + [tree] * 8)  # no catheter before the contrast
    assert precontrast_frames(empty_start) is None
    assert not precontrast_catheter(tree, None).any()

"""2D segmentation scores: Dice and clDice of binary masks (for the benchmark and tests).

Reads/writes nothing. clDice (Shit et al. 2021) = 2·Tprec·Tsens/(Tprec+Tsens), Tprec = |S(P)∩G|/|S(P)|,
Tsens = |S(G)∩P|/|S(G)|, with S the 2D morphological skeleton (:func:`skimage.morphology.skeletonize`).
Both empty → 1; one empty → 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["dice_2d", "cldice_2d"]


def dice_2d(pred, truth) -> float:
    p, g = np.asarray(pred, bool), np.asarray(truth, bool)
    s = p.sum() + g.sum()
    return 1.0 if s == 0 else float(2 * (p & g).sum() / s)


def cldice_2d(pred, truth) -> float:
    from skimage.morphology import skeletonize

    p, g = np.asarray(pred, bool), np.asarray(truth, bool)
    if not p.any() and not g.any():
        return 1.0
    if not p.any() or not g.any():
        return 0.0
    sp, sg = skeletonize(p), skeletonize(g)
    tprec = (sp & g).sum() / max(sp.sum(), 1)
    tsens = (sg & p).sum() / max(sg.sum(), 1)
    return float(0.0 if tprec + tsens == 0 else 2 * tprec * tsens / (tprec + tsens))

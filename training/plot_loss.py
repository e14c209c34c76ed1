"""Redraw docs/img/sbp_training_loss.png: the shipped SBP network's loss over all its training stages.

Each stage's log (training/*.csv, see README.md) counts its steps from 1; they are joined on one axis
(stage k's step + the steps of the stages before it) and drawn by :func:`stages.sbp.train.plot_log`.

Run: python training/plot_loss.py
"""

from __future__ import annotations

import csv
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

# (log, steps of that stage, pairs per step) in training order; the last five stages accumulated four pairs
# per optimiser step (--accum 4), the ninth widened the network first (--init with wider widths), the
# tenth trained on twice the trees (seeds 0-119), the eleventh on three times (seeds 0-179) and the
# twelfth on four times (seeds 0-239)
STAGES = [("sbp_log.csv", 1300, 1), ("sbp_finetune_log.csv", 1000, 1), ("sbp_finetune2_log.csv", 1200, 1),
          ("sbp_finetune3_log.csv", 1000, 1), ("sbp_finetune4_log.csv", 800, 1), ("sbp_finetune5_log.csv", 1000, 1),
          ("sbp_finetune6_log.csv", 1000, 1), ("sbp_finetune7_log.csv", 250, 4), ("sbp_finetune8_log.csv", 210, 4),
          ("sbp_finetune9_log.csv", 200, 4), ("sbp_finetune10_log.csv", 200, 4), ("sbp_finetune11_log.csv", 200, 4),
          ("sbp_finetune12_log.csv", 200, 4)]
COLUMNS = ["step", "loss", "dice_occ", "bce_occ", "dice_cen", "bce_cen", "candidate_recall", "seconds"]


def main() -> int:
    from stages.sbp.train import plot_log

    rows, pairs, offset = [], [], 0
    for name, steps, per_step in STAGES:
        for r in csv.DictReader(open(HERE / name)):
            row = {k: r[k] for k in COLUMNS}
            row["step"] = int(float(r["step"])) + offset
            rows.append(row)
            pairs.append(per_step)
        offset += steps
    with tempfile.TemporaryDirectory() as tmp:
        joined = Path(tmp) / "all_stages.csv"
        with open(joined, "w", newline="") as fh:
            writer = csv.DictWriter(fh, COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
        out = plot_log(joined, ROOT / "docs" / "img" / "sbp_training_loss.png", pairs_per_step=pairs)
    print(f"{out}: {len(rows)} logged steps of {offset}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

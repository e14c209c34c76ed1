"""Give a newly trained stage's weights the lineage of the weights it continued.

`autocar train` records only its own run in a weights file's ``meta``; the shipped file carries every
stage (``stages``), the overall ``step``, ``pairs_seen`` and the summed step time, which the model card and
Table 1 (benchmarks/table1.py::weights_note) read. Run it once per shipped stage:

    python training/chain_meta.py PREVIOUS.pt NEW.pt --init "stage 9 weights (step 7760)" \
        --note "fresh AdamW, ..." [--data "..."]

NEW.pt is rewritten in place (atomically); its tensors are not touched.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    import torch

    from stages.core.artefacts import atomic_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("previous", type=Path, help="weights the new stage started from (with their lineage)")
    ap.add_argument("new", type=Path, help="the new stage's model.pt (rewritten in place)")
    ap.add_argument("--log", type=Path, required=True, help="the new stage's log.csv (step seconds)")
    ap.add_argument("--init", required=True, help="what the new stage started from, in words")
    ap.add_argument("--note", required=True, help="how the stage was run, in words")
    ap.add_argument("--data", default=None, help="training data of the new stage (default: the previous one's)")
    args = ap.parse_args(argv)

    old = torch.load(args.previous, map_location="cpu", weights_only=False)["meta"]
    new = torch.load(args.new, map_location="cpu", weights_only=False)
    run = new["meta"]
    with open(args.log, newline="") as f:
        seconds = [float(r["seconds"]) for r in csv.DictReader(f)]
    steps = int(run["summary"]["steps"])
    # every optimiser step averages accum pairs on each data-parallel rank
    pairs = steps * int(run["train"].get("accum", 1)) * int(run["summary"].get("world_size", 1))
    stage = {"steps": steps, "pairs": pairs, "init": args.init, "train": run["train"],
             "step_seconds_total": round(sum(seconds), 1), "median_seconds_per_step": round(statistics.median(seconds), 3),
             "train_cases": run["summary"].get("train_cases"), "val_cases": run["summary"].get("val_cases"),
             "note": args.note}
    meta = {k: v for k, v in old.items() if k != "stages"}
    meta.update(step=int(old["step"]) + steps, pairs_seen=int(old["pairs_seen"]) + pairs,
                step_seconds_total=round(float(old["step_seconds_total"]) + sum(seconds), 1),
                median_seconds_per_step=stage["median_seconds_per_step"], train=run["train"],
                stages=[*old["stages"], stage])
    if args.data:
        meta["data"] = args.data
    new["meta"] = meta
    with atomic_path(args.new) as tmp:
        torch.save(new, tmp)
    print(f"{args.new}: step {meta['step']}, {meta['pairs_seen']} pairs, {len(meta['stages'])} stages")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

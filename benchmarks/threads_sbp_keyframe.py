"""The SBP network on one key frame at N torch threads, as it runs in `autocar reconstruct` (issue 36,
finding 1: the default thread count). Needs a reconstruction's predictions.zarr (its masks and cameras):

    autocar reconstruct examples/run_a.dcm examples/run_b.dcm -o /tmp/y
    python benchmarks/threads_sbp_keyframe.py /tmp/y/predictions.zarr --threads 1 2 1 2

Each count runs in its own process (torch's pools are set when it starts). Prints one line per run with the
load average; docs/benchmarks/threads_under_load.md holds the figures measured on the shared machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = """
import os, sys, time
import torch
torch.set_num_threads({n})
from stages.graph.io import read_sparse_predictions
from stages.methods3d import load_predictor
_, frames = read_sparse_predictions({path!r})
f = frames[0]
predict = load_predictor("sbp")
t0 = time.perf_counter()
vox = predict(f.masks["a"].astype(bool), f.masks["b"].astype(bool), f.cameras["a"], f.cameras["b"], "left")
print(f"{n} thread(s): {{time.perf_counter() - t0:.1f}} s, {{len(vox)}} voxels, load average {{os.getloadavg()[0]:.2f}}")
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("predictions", type=Path)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args(argv)
    for n in args.threads:
        env = {**os.environ, "OMP_NUM_THREADS": str(n)}
        subprocess.run([sys.executable, "-c", CHILD.format(n=n, path=str(args.predictions))], cwd=REPO, env=env,
                       check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

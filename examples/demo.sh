#!/usr/bin/env bash
# `make demo`: reconstruct the bundled example (two simulated XA runs, examples/run_a.dcm + run_b.dcm).
# Uses the shipped networks (stages/weights/sbp.pt, seg.pt); where one is not shipped yet it falls back
# to the documented baseline (visual hull / vesselness) and says so.
set -euo pipefail
out=${1:-out/demo}
here=$(cd "$(dirname "$0")" && pwd)
py=${PYTHON:-$here/../.venv/bin/python}
autocar=${AUTOCAR:-$here/../.venv/bin/autocar}
weights=$("$py" -c 'import stages, pathlib; print(pathlib.Path(stages.__file__).parent / "weights")')
method=sbp
seg=unet
if [ ! -f "$weights/sbp.pt" ]; then
  echo "note: no shipped SBP weights ($weights/sbp.pt): reconstructing with the visual-hull baseline"
  method=visual-hull
fi
if [ ! -f "$weights/seg.pt" ]; then
  echo "note: no shipped segmentation weights ($weights/seg.pt): segmenting with multiscale vesselness"
  seg=vesselness
fi
mkdir -p "$out"
echo "== geometry of the bundled runs"
"$autocar" info "$here/run_a.dcm" "$here/run_b.dcm"
echo "== reconstruct (method: $method, segmentation: $seg)"
"$autocar" reconstruct "$here/run_a.dcm" "$here/run_b.dcm" -o "$out" --method "$method" --seg-method "$seg" --force  # a rerun replaces the last one
echo "== done: open $out/report.html (3D model, overlays, timings); per key frame .vtp/.stl/.json in $out"

#!/usr/bin/env bash
# `make demo`: reconstruct the bundled example (two simulated XA runs, examples/run_a.dcm + run_b.dcm).
# Uses autocar's default 3D method (the explicit two-view correspondence, stages/methods3d.DEFAULT_METHOD: no
# weights) and the shipped segmenter (stages/weights/seg.pt); without the segmenter's weights it falls back
# to multiscale vesselness and says so. METHOD=sbp bash examples/demo.sh runs the SBP network instead.
set -euo pipefail
out=${1:-out/demo}
here=$(cd "$(dirname "$0")" && pwd)
py=${PYTHON:-$here/../.venv/bin/python}
autocar=${AUTOCAR:-$here/../.venv/bin/autocar}
weights=$("$py" -c 'import stages, pathlib; print(pathlib.Path(stages.__file__).parent / "weights")')
method=${METHOD:-$("$py" -c 'from stages.methods3d import DEFAULT_METHOD; print(DEFAULT_METHOD)')}
seg=unet
if [ "$method" = sbp ] && [ ! -f "$weights/sbp.pt" ]; then
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

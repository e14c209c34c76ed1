#!/usr/bin/env bash
# `make demo`: the furthest pipeline stages that work today, on built-in and bundled data.
# (When `autocar reconstruct` lands, this becomes: reconstruct the bundled example runs.)
set -euo pipefail
out=${1:-out/demo}
here=$(cd "$(dirname "$0")" && pwd)
autocar=${AUTOCAR:-$here/../.venv/bin/autocar}
mkdir -p "$out"

echo "== 1. built-in clinical pose model (nine standard projections)"
"$autocar" fit-poses --default -o "$out/poses.zarr"

echo "== 2. geometry of sample runs"
runs=( "$here"/*.dcm )
if [ ! -e "${runs[0]}" ] && [ -d "$here/../../shared/data/phantom_xa" ]; then
  runs=( "$here/../../shared/data/phantom_xa/IM1.dcm" "$here/../../shared/data/phantom_xa/IM5.dcm" )
fi
if [ -e "${runs[0]}" ]; then
  "$autocar" info "${runs[@]}"
else
  echo "(no sample DICOM run found: examples/*.dcm or ../shared/data/phantom_xa)"
fi

echo "== done: outputs in $out (poses.zarr, poses.png)"

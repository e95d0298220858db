#!/usr/bin/env bash
# The eight synthetic KITTI-rig drives behind VSeq2PC's training and figures, as feature caches: six
# training cities (seeds 5, 11, 13, 17, 19, 29), a validation city (23) and a held-out city (7). Each
# drive is rendered to a bag (front camera with depth + labels, 64-beam labelled LiDAR), turned into a
# cache (vseq2pc_cache) and the bag removed (several GB of raw images). Existing caches are kept.
# About 3 minutes per drive on one core of an AMD EPYC; LANES=2 renders two drives at a time (all eight:
# 11 minutes).
#
#   [LANES=2] bash benchmarks/recipes/vseq2pc_drives.sh OUT [citysim option ...]
#   e.g. bash benchmarks/recipes/vseq2pc_drives.sh out/vseq2pc/exact --depth-range 0 --depth-noise 0
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:?usage: vseq2pc_drives.sh OUT [citysim option ...]}
shift
LANES=${LANES:-1}
mkdir -p "$OUT"
DRIVES=("train_seed5 5 1000" "train_seed11 11 1000" "train_seed13 13 1000" "train_seed17 17 1000"
        "train_seed19 19 1000" "train_seed29 29 1000" "val_seed23 23 1000" "heldout_seed7 7 800")

render() {  # name, seed, frames, citysim options...
  local name=$1 seed=$2 frames=$3
  shift 3
  [ -f "$OUT/$name.npz" ] && return 0
  $PY -m citysim.cli --rig kitti --frames "$frames" --seed "$seed" --keyframe-spacing 1.5 --image-size 620x188 \
      --workers 1 --no-progress --out "$OUT/$name.bag" --overwrite "$@"
  $PY -m lcpr_offline.vseq2pc_cache "$OUT/$name.bag" --out "$OUT/$name.npz"
  rm -rf "$OUT/$name.bag"
}

lane() {  # lane number: renders every LANES-th drive from it
  local i
  for ((i = $1; i < ${#DRIVES[@]}; i += LANES)); do
    # shellcheck disable=SC2086
    render ${DRIVES[$i]} "${@:2}"
  done
}

pids=()
for ((l = 0; l < LANES; l++)); do
  lane "$l" "$@" &
  pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done

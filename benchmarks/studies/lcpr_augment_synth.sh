#!/usr/bin/env bash
# LCPR trained with the paper's robustness augmentations (yaw by camera slots, lighting, a camera
# blacked out) by exactly the recipe of benchmarks/studies/lcpr_train_synth.sh (drives seeds 1 and 2, 12
# epochs of 64 queries), then compared with the bundled weights (the same recipe without
# augmentation): lcpr_eval on the validation city (seed 3) and the robustness studies
# (benchmarks/studies/lcpr_robustness.py) on the held-out cities. The augmentation settings are fixed here
# before any held-out city is run, never chosen on one.
#
#   bash benchmarks/studies/lcpr_augment_synth.sh [OUT]      (default OUT=out/train_synth, shared with lcpr_train_synth.sh)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/train_synth}
mkdir -p "$OUT"

for s in 1 2 3; do
  [ -d "$OUT/synth_s$s.bag" ] || $PY -m citysim.cli --seed $s --frames 300 --image-size 400x225 \
      --workers 2 --no-progress --out "$OUT/synth_s$s.bag"
done

$PY -m lcpr_offline.lcpr_train "$OUT/synth_s1.bag" "$OUT/synth_s2.bag" --out "$OUT/run_augmented" \
    --cache "$OUT/cache" --preset cpu --epochs 12 --queries-per-epoch 64 --batch 2 --lr 3e-4 --step-epochs 4 \
    --gamma 0.8 --fractions 0.6 0.2 0.2 --threads 2 --seed 0 --quiet \
    --augment-yaw 0.5 --augment-lighting 0.5 --brightness 0.3 1.6 --augment-camera-drop 0.2
$PY -m lcpr_offline.lcpr_train --export "$OUT/run_augmented/best.pth" "$OUT/lcpr_augmented.pth"

for w in "augmented $OUT/lcpr_augmented.pth" "bundled weights/lcpr_synth_narrow.pth"; do
  set -- $w
  $PY -m lcpr_ros.evaluate "$OUT/synth_s3.bag" --weights "$2" --threads 2 --quiet --no-verify --out "$OUT/val_s3_$1"
  $PY benchmarks/studies/lcpr_robustness.py --weights "$2" --cities grid:7 grid:9 --out "$OUT/robust_$1"
  $PY benchmarks/studies/lcpr_robustness.py --weights "$2" --cities kitti00:21 --frames 900 --out "$OUT/robust_k00_$1"
done

#!/usr/bin/env bash
# Does VSeq2PC's sequence help once the camera depth is what a depth network gives? The study behind
# citysim's network-like depth (citysim/depthnet.py). The same short training (1 stage-1 + 4 stage-2
# epochs of 3520 queries, the bundled recipe's options) on the six training drives of
# benchmarks/recipes/vseq2pc_train_synth.sh twice: with the renderer's exact depth (drives rendered with --depth-range 0
# --depth-noise 0 into OUT/exact), and with the cache features of that depth limited to 25 m and 10 %
# noise (benchmarks/studies/vseq2pc_depth_range.py; both settings fixed before any run). Each is scored on the
# validation drive (seed 23) with the full sequence, 1, 2 and 3 frames, and the network-free feature
# match. The held-out drive (seed 7) is not read. About 16 minutes per variant (4 epochs) on 2 cores of
# an AMD EPYC, plus about 11 minutes for the drives when OUT/exact has none.
#
#   bash benchmarks/studies/vseq2pc_depth_study.sh [OUT] [EPOCHS] [VARIANT ...]
#   (default OUT=out/vseq2pc; EPOCHS=4 stage-2 epochs; VARIANT exact_depth and/or depth25, default both)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/vseq2pc}
EPOCHS=${2:-4}
VARIANTS=("${@:3}")
[ ${#VARIANTS[@]} -gt 0 ] || VARIANTS=(exact_depth depth25)
EXACT="$OUT/exact"
LIMITED="$OUT/depth25"
LANES=${LANES:-2} bash benchmarks/recipes/vseq2pc_drives.sh "$EXACT" --depth-range 0 --depth-noise 0
[ -f "$LIMITED/val_seed23.npz" ] || $PY benchmarks/studies/vseq2pc_depth_range.py "$EXACT"/train_seed{5,11,13,17,19,29}.npz \
    "$EXACT/val_seed23.npz" --out "$LIMITED" --max-depth 25 --noise 0.1

study() {  # name, cache folder
  local name=$1 caches=$2 run="$OUT/depth_study_$1"
  [ "$EPOCHS" = 4 ] || run="${run}_e$EPOCHS"
  [ -f "$run/history.json" ] && grep -q "\"epoch\": $EPOCHS" "$run/history.json" || \
    $PY -m lcpr_offline.vseq2pc_train --cache "$caches"/train_seed{5,11,13,17,19,29}.npz \
      --val-cache "$caches/val_seed23.npz" --out "$run" --pretrain-epochs 1 --epochs "$EPOCHS" --batch 32 \
      --queries-per-epoch 3520 --seq-base-lr 8e-3 --seq-warmup-epochs 0.5 --negatives 1 --mixed-batch-norm \
      --ranking-weight 1 --reconstruction-weight 10 --select recall_at_1 --no-progress
  $PY -m lcpr_offline.vseq2pc_evaluate --cache "$caches/val_seed23.npz" --weights-dir "$run" --which best \
    --name "$name" --single-frame --sequence-lengths 2 3 --feature-match --out "$run/eval_val"
}
for variant in "${VARIANTS[@]}"; do
  case $variant in
    exact_depth) study exact_depth "$EXACT" ;;
    depth25) study depth25 "$LIMITED" ;;
    *) echo "variant $variant: expected exact_depth or depth25" >&2; exit 2 ;;
  esac
done

#!/usr/bin/env bash
# VSeq2PC on the synthetic city (KITTI-like rig): train on one drive, evaluate on a held-out
# drive (another seed and city), trained vs untrained vs a network-free feature match.
# These are the commands behind the figures in README ("VSeq2PC"). ~30 min on 2 shared cores.
#
#   bash benchmarks/vseq2pc_train_synth.sh [OUT]      (default OUT=out/vseq2pc)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/vseq2pc}
mkdir -p "$OUT"

# 1. drives (front camera with depth + labels, 64-beam labelled LiDAR), then per-frame feature caches
for pair in "train_seed5 5 1000" "heldout_seed7 7 800"; do
  set -- $pair
  [ -f "$OUT/$1.npz" ] && continue
  $PY -m msg_tools.synth.cli --rig kitti --frames "$3" --seed "$2" --keyframe-spacing 1.5 --image-size 620x188 \
      --workers 1 --no-progress --out "$OUT/$1.bag"
  $PY -m lcpr_core.vseq2pc.dataset "$OUT/$1.bag" --out "$OUT/$1.npz"
  rm -rf "$OUT/$1.bag"   # several GB of raw images; the cache is all training needs
done

# 2. stage 1 (reconstruction) + stage 2 (joint), then 3 more stage-2 epochs with in-batch negatives
$PY -m lcpr_core.vseq2pc.train --cache "$OUT/train_seed5.npz" --out "$OUT/run1" --pretrain-epochs 2 --epochs 5 \
    --batch 16 --queries-per-epoch 320 --seq-base-lr 2.4e-3 --seq-warmup-epochs 0.5 --negatives 2
$PY -m lcpr_core.vseq2pc.train --cache "$OUT/train_seed5.npz" --out "$OUT/run2" \
    --init-sequence "$OUT/run1/sequence_model.pth" --init-descriptor "$OUT/run1/descriptor_model.pth" \
    --pretrain-epochs 0 --epochs 3 --batch 16 --queries-per-epoch 320 --seq-base-lr 2.4e-3 \
    --seq-warmup-epochs 0.5 --negatives 1 --in-batch

# 3. the paper's evaluation on the held-out drive
$PY -m lcpr_core.vseq2pc.evaluate --cache "$OUT/heldout_seed7.npz" --weights-dir "$OUT/run2" --name "trained (run2)" \
    --untrained --single-frame --feature-match --out "$OUT/eval_run2"

#!/usr/bin/env bash
# VSeq2PC on the synthetic city (KITTI-like rig): train on six drives (seeds 5, 11, 13, 17, 19,
# 29), pick the epoch by Recall@1 on a validation drive (seed 23), evaluate on a held-out drive (seed 7):
# each drive is a city of its own. Trained vs untrained vs a network-free feature match. These
# are the commands behind the figures in README ("VSeq2PC") and the bundled
# weights/vseq2pc_synth_*.pth. About 75 minutes on 2 idle cores of an AMD EPYC (drives 11 min, two at a
# time; training 62 min; evaluation ~2 min).
#
# The drives' depth images are what a monocular depth network gives (citysim's default for the kitti rig:
# none beyond 25 m along the optical axis, a smooth 10 % error), not the renderer's exact depth: with
# exact depth one frame already holds 86 % of the LiDAR's forward structure and the sequence has nothing
# to add (README "VSeq2PC", benchmarks/studies/vseq2pc_depth_study.sh).
#
#   bash benchmarks/recipes/vseq2pc_train_synth.sh [OUT] [--bundle]   (default OUT=out/vseq2pc)
#
# --bundle copies the weights with the best validation Recall@1 to weights/vseq2pc_synth_*.pth.
# The exact-depth set (weights/vseq2pc_synth_exact_*.pth; made on the 2-core Intel Xeon, 39 min of training):
#
#   DRIVE_OPTS="--depth-range 0 --depth-noise 0" EPOCHS=12 \
#     bash benchmarks/recipes/vseq2pc_train_synth.sh out/vseq2pc/exact --bundle-exact
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/vseq2pc}
case "${2:-}" in  # where --bundle copies the weights, checked before the hour of work
  --bundle) prefix=weights/vseq2pc_synth_ ;;
  --bundle-exact) prefix=weights/vseq2pc_synth_exact_ ;;
  "") prefix= ;;
  *) echo "vseq2pc_train_synth.sh: unknown option '$2' (accepted: --bundle, --bundle-exact)" >&2; exit 2 ;;
esac
mkdir -p "$OUT"

# 1. the eight drives as feature caches (front camera with depth + labels, 64-beam labelled LiDAR)
# shellcheck disable=SC2086
LANES=${LANES:-2} bash benchmarks/recipes/vseq2pc_drives.sh "$OUT" ${DRIVE_OPTS:-}

# 2. stage 1 (reconstruction, 1 epoch) + stage 2 (joint, 16 epochs of 3520 queries, in-batch pairs, batch
#    norm with the statistics eval mode uses, the ranking term, stage 1's reconstruction kept; README
#    "VSeq2PC" and benchmarks/studies/vseq2pc_loss_study.sh say why); the epoch with the best Recall@1 on the
#    validation drive is kept as best_*
$PY -m lcpr_offline.vseq2pc_train --cache "$OUT"/train_seed{5,11,13,17,19,29}.npz --val-cache "$OUT/val_seed23.npz" \
    --out "$OUT/run" --pretrain-epochs 1 --epochs "${EPOCHS:-16}" --batch 32 --queries-per-epoch 3520 --seq-base-lr 8e-3 \
    --seq-warmup-epochs 0.5 --negatives 1 --mixed-batch-norm --ranking-weight 1 --reconstruction-weight 10 \
    --select recall_at_1 --no-progress

# 3. the paper's evaluation on the held-out drive
$PY -m lcpr_offline.vseq2pc_evaluate --cache "$OUT/heldout_seed7.npz" --weights-dir "$OUT/run" --which best \
    --name "trained" --untrained --single-frame --sequence-lengths 2 3 --feature-match --out "$OUT/eval"

if [ -n "$prefix" ]; then
  cp "$OUT/run/best_sequence_model.pth" "${prefix}sequence.pth"
  cp "$OUT/run/best_descriptor_model.pth" "${prefix}descriptor.pth"
fi

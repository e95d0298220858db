#!/usr/bin/env bash
# Train the narrow CPU LCPR on the corpus of benchmarks/recipes/lcpr_corpus.sh (12 training cities), pick the
# epoch on validation queries of the training cities, take the operating threshold (max F1, online
# protocol) on the validation cities, then report on the test cities (never used before this step).
# One run from scratch: the recipe of the previous bundled weights (20 epochs); the bundled weights now
# continue the configuration search's run instead (benchmarks/recipes/lcpr_bundle.py).
#
#   bash benchmarks/studies/lcpr_train_corpus.sh [CORPUS] [EPOCHS] [QUERIES_PER_EPOCH] [extra lcpr_train options]
#   (default CORPUS=out/corpus, 20 epochs of 256 queries; e.g. --augment-yaw 0.5 --augment-lighting 0.5)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/corpus}
EPOCHS=${2:-20}
QUERIES=${3:-256}
shift $(( $# < 3 ? $# : 3 ))
RUN="$OUT/run"

$PY -m lcpr_offline.lcpr_train "$OUT"/train_*.bag --out "$RUN" --cache "$OUT/cache" --preset cpu \
    --epochs "$EPOCHS" --queries-per-epoch "$QUERIES" --batch 4 --lr 3e-4 --step-epochs 6 --gamma 0.8 \
    --fractions 0.8 0.1 0.1 --threads 2 --seed 0 --quiet "$@"
$PY -m lcpr_offline.lcpr_train --export "$RUN/best.pth" "$OUT/lcpr_corpus_narrow.pth"

for split in val test; do
  for bag in "$OUT"/${split}_*.bag; do
    name=$(basename "$bag" .bag)
    $PY -m lcpr_ros.evaluate "$bag" --weights "$OUT/lcpr_corpus_narrow.pth" --threads 2 --quiet --no-verify \
        --out "$OUT/eval_$name"
  done
done
$PY benchmarks/tools/eval_table.py "$OUT"

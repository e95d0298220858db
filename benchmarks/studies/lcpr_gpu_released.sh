#!/usr/bin/env bash
# The released LCPR configuration (width 1.0, six 256x704 images, 32x1056 range images) trained on a GPU
# on the corpus of benchmarks/recipes/lcpr_corpus.sh, then evaluated there on the validation and test cities (online protocol,
# geometric verification off, Scan Context alongside) as the bundled narrow weights are.
#
#   bash benchmarks/studies/lcpr_gpu_released.sh [OUT] [SECONDS]
#
# SECONDS (default 3600) is the wall time of the whole script: training gets what rendering and caching
# leave, less RESERVE seconds (default 150) kept for the whitening and the evaluations, and stops between
# epochs (lcpr_train --time-budget). Written for one GPU and 16 cores; nothing here picks a setting on a
# test city: the epoch comes from the training cities' validation queries, the whitening is fitted on the
# training cities, and the recipe below was fixed before any run.
#
# Environment: PYTHON (default .venv/bin/python), DEVICE (cuda:0), AMP (bf16), PRESET (released),
# FRAMES / LONG_FRAMES (corpus size, 300 / 900), JOBS / WORKERS (renders at a time / processes each, 8 / 2),
# RETURN_DIR: when set, the reports, logs and curve go there as results.tar.gz and the float16 weights
# (whitened, turn-averaged) as weights.pth.part-* of at most 15 MiB (cat them back together).
set -euo pipefail
cd "$(dirname "$0")/../.."
START=$(date +%s)
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/gpu_released}
TOTAL=${2:-3600}
RESERVE=${RESERVE:-150}
DEVICE=${DEVICE:-cuda:0}
AMP=${AMP:-bf16}
PRESET=${PRESET:-released}
CORPUS=$OUT/corpus
RUN=$OUT/run
mkdir -p "$OUT"
elapsed() { echo $(( $(date +%s) - START )); }
stamp() { echo "[$(elapsed) s] $*"; }

stamp "rendering the corpus (JOBS=${JOBS:-8} x WORKERS=${WORKERS:-2})"
JOBS=${JOBS:-8} WORKERS=${WORKERS:-2} bash benchmarks/recipes/lcpr_corpus.sh "$CORPUS" "${FRAMES:-300}" "${LONG_FRAMES:-900}" \
  >/dev/null
for log in "$CORPUS"/*.log; do  # the cities' own reports: compare with a corpus rendered elsewhere
  echo "$(basename "$log" .log): $(grep -h '^frames:\|^revisits:\|^points:' "$log" | tr -s ' ' | tr '\n' ';')"
done

stamp "preprocessing the training cities ($PRESET inputs)"
$PY - "$OUT/cache" "$PRESET" "${CACHE_WORKERS:-12}" "$CORPUS"/train_*.bag <<'PY'
import sys
from lcpr_offline.lcpr_cache import build_cache
from lcpr_core.lcpr.training.config import input_preset
cache = build_cache(sys.argv[4:], sys.argv[1], inputs=input_preset(sys.argv[2]), progress=False,
                    workers=int(sys.argv[3]))
print(f"cache: {len(cache)} samples, {cache.images.nbytes / 2**30:.1f} GiB of images, "
      f"built in {cache.meta['build_seconds']:.0f} s")
PY

train() {  # AMP: the recipe below was fixed before any run
  local budget=$(( TOTAL - $(elapsed) - RESERVE ))
  [ "$budget" -ge 60 ] || budget=60  # at least the first epoch (0 would mean no budget)
  stamp "training for at most $budget s on $DEVICE (amp $1)"
  $PY -m lcpr_offline.lcpr_train "$CORPUS"/train_*.bag --out "$RUN" --cache "$OUT/cache" --preset "$PRESET" \
    --device "$DEVICE" --amp "$1" --time-budget "$budget" --epochs 200 --queries-per-epoch 768 --batch 8 \
    --lr 1e-4 --step-epochs 10 --gamma 0.8 --fractions 0.8 0.1 0.1 --eval-batch 32 --threads 8 --seed 0 --quiet
}
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || true
train "$AMP" || { [ "$AMP" != off ] && rm -rf "$RUN" && echo "amp $AMP failed; float32 instead" && train off; }
nvidia-smi --query-gpu=memory.used --format=csv,noheader 2>/dev/null || true

stamp "whitening (fitted on the training cities) and turn averaging"
$PY -m lcpr_offline.lcpr_train "$CORPUS"/train_*.bag --cache "$OUT/cache" --whiten "$RUN/best.pth" \
  "$RUN/whitened.pth" --device "$DEVICE" --eval-batch 32 --quiet
$PY -m lcpr_offline.lcpr_train --turn-average on "$RUN/whitened.pth" "$RUN/turned.pth"

LIMIT=$(( TOTAL - $(elapsed) - 30 ))  # every evaluation ends in time for the results below
[ "$LIMIT" -ge 60 ] || LIMIT=60
stamp "evaluating on the validation and test cities (each stopped after $LIMIT s)"
pids=()
for bag in "$CORPUS"/val_*.bag "$CORPUS"/test_*.bag; do
  name=$(basename "$bag" .bag)
  for variant in best turned; do  # one pass as trained; whitened and averaged over the six turns
    timeout "$LIMIT" $PY -m lcpr_ros.evaluate "$bag" --weights "$RUN/$variant.pth" --device "$DEVICE" --precision fp32 \
      --threads 2 --quiet --no-verify --out "$OUT/eval_${variant}_$name" >"$OUT/eval_${variant}_$name.log" 2>&1 &
    pids+=("$!")
  done
done
for pid in "${pids[@]}"; do wait "$pid" || echo "an evaluation failed (see $OUT/eval_*.log)"; done

stamp "results"
$PY benchmarks/tools/eval_table.py "$OUT"
if [ -n "${RETURN_DIR:-}" ]; then
  mkdir -p "$RETURN_DIR"
  $PY -m lcpr_offline.lcpr_train --export "$RUN/turned.pth" "$OUT/lcpr_released_gpu.pth"
  split -b 15M -d "$OUT/lcpr_released_gpu.pth" "$RETURN_DIR/weights.pth.part-"
  sha256sum "$OUT/lcpr_released_gpu.pth"
  (cd "$OUT" && tar -czf "$RETURN_DIR/results.tar.gz" $(ls -d run/*.json run/*.png eval_*/report.json eval_*.log \
    corpus/*.log 2>/dev/null)) || echo "results.tar.gz is incomplete"
fi
stamp "done"

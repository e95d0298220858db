#!/usr/bin/env bash
# Train the narrow CPU LCPR on two synthetic drives and compare it, on a held-out drive of
# another seed (another street graph and city), with its seeded initialisation and Scan Context.
# This is the recipe of the earlier bundled weights (README "Training": "earlier bundled weights");
# the bundled weights now come from benchmarks/recipes/lcpr_corpus.sh, lcpr_config_search.py and lcpr_bundle.py. On 2 idle cores the
# training takes ~4 min (15-25 s per epoch); on a shared machine it took 25 min.
#
#   bash benchmarks/studies/lcpr_train_synth.sh [OUT]      (default OUT=out/train_synth)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/train_synth}
mkdir -p "$OUT"

# 1. drives: seeds 1 and 2 for training, seed 7 held out (300 keyframes each, 5 m apart, ~80 s each)
for s in 1 2 7; do
  [ -d "$OUT/synth_s$s.bag" ] || $PY -m citysim.cli --seed $s --frames 300 --image-size 400x225 \
      --workers 2 --no-progress --out "$OUT/synth_s$s.bag"
done

# 2. training: cpu preset (6 x 64x192 images, 16x288 range image, width 0.25), 12 epochs of 64 queries
$PY -m lcpr_offline.lcpr_train "$OUT/synth_s1.bag" "$OUT/synth_s2.bag" --out "$OUT/run" --preset cpu \
    --epochs 12 --queries-per-epoch 64 --batch 2 --lr 3e-4 --step-epochs 4 --gamma 0.8 \
    --fractions 0.6 0.2 0.2 --threads 2 --seed 0 --quiet

# 3. the small float16 copy that ships as weights/lcpr_synth_narrow.pth
$PY -m lcpr_offline.lcpr_train --export "$OUT/run/best.pth" "$OUT/lcpr_synth_narrow.pth"

# 4. held-out drive: trained (with the Scan Context baseline) and the seeded initialisation
$PY -m lcpr_ros.evaluate "$OUT/synth_s7.bag" --weights "$OUT/lcpr_synth_narrow.pth" --threads 2 --quiet \
    --out "$OUT/heldout_trained"
$PY -m lcpr_ros.evaluate "$OUT/synth_s7.bag" --weights "$OUT/run/init.pth" --threads 2 --quiet \
    --no-scan-context --out "$OUT/heldout_init"

# 5. operating threshold of those weights (then lcpr_core.pretrained.BUNDLED_MAX_DISTANCE): the max-F1
#    threshold of the online protocol on a validation city of its own (seed 3)
[ -d "$OUT/synth_s3.bag" ] || $PY -m citysim.cli --seed 3 --frames 300 --image-size 400x225 \
    --workers 2 --no-progress --out "$OUT/synth_s3.bag"
$PY -m lcpr_ros.evaluate "$OUT/synth_s3.bag" --weights "$OUT/lcpr_synth_narrow.pth" --threads 2 --quiet \
    --out "$OUT/val_s3"
$PY -c "import json, sys; r = json.load(open(sys.argv[1])); print('max-F1 threshold:', r['methods'][0]['online']['max_f1_threshold'])" "$OUT/val_s3/report.json"

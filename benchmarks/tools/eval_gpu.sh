#!/usr/bin/env bash
# lcpr_eval's keyframes per second on a lent GPU machine, in one run: retrieval only at the released size
# (benchmarks/tools/eval_throughput.py, seeded weights), then lcpr_eval with verification on (bundled weights,
# one verification process per core), on a synthetic nuScenes-rig drive of six 1600 x 900 JPEGs a frame.
# Every line of $OUT/result.log names the GPU and the CPU it was measured on.
#
#   bash benchmarks/tools/eval_gpu.sh [BAG]                     # on the lent machine (repository root)
#   DEVICE=cpu FRAMES=30 bash benchmarks/tools/eval_gpu.sh      # the whole script on a CPU-only machine
#
# Settings (environment): DEVICE (cuda; cpu runs everything on the CPU), FRAMES (240: the drive rendered when no
# BAG is given), BATCHES ("16 32 16": frames per network call; the first run of a process pays nvJPEG's and the
# allocator's first calls, about 0.8 s, so batch 16 is measured again after it), WORKERS (verification processes:
# 16 on cuda, every core on cpu), OUT (out/eval_gpu when unset), WORK (/tmp/eval_gpu: the drive and lcpr_eval's
# outputs), PYTHON (.venv/bin/python where it exists, else python3).
#
# The lent machine has Python 3.12 with its own CUDA torch, torchvision, onnxruntime, numpy, opencv, matplotlib;
# what else the project imports travels as wheels in the ignored .whl folder (carry: [".whl"]), made here with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
#     --platform manylinux2014_x86_64 -d .whl \
#     faiss-cpu small_gicp rosbags backports.zstd apsw lz4 zstandard ruamel.yaml pykdtree
# (about 30 MB). They are installed into /tmp/site; without a .whl folder, or under another Python than 3.12,
# that step is skipped and the Python's own packages are used.
set -uo pipefail

DEVICE=${DEVICE:-cuda}
FRAMES=${FRAMES:-240}
BATCHES=${BATCHES:-16 32 16}
WORK=${WORK:-/tmp/eval_gpu}
OUT=${OUT:-out/eval_gpu}
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
case "$DEVICE" in
  cuda) WORKERS=${WORKERS:-16}; render_s=120; throughput_s=180; eval_s=180 ;;
  cpu) WORKERS=${WORKERS:-$(nproc)}; render_s=300; throughput_s=600; eval_s=600 ;;
  *) echo "eval_gpu: DEVICE=$DEVICE; accepted: cuda, cpu" >&2; exit 2 ;;
esac
if [ ! -f lcpr_core/__init__.py ]; then
  echo "eval_gpu: run from the repository root (no lcpr_core/ in $PWD)" >&2; exit 2
fi
mkdir -p "$OUT" "$WORK" || exit 2
: > "$OUT/result.log"
start=$SECONDS

# 1. the carried wheels
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
py_version=$("$PYTHON" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")') || exit 2
if ! compgen -G ".whl/*.whl" >/dev/null; then
  wheels="wheels: skipped (no .whl/*.whl here)"
elif [ "$py_version" != 3.12 ]; then
  wheels="wheels: skipped (.whl holds Python 3.12 wheels; $PYTHON is $py_version)"
else
  "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PYTHONPATH
  wheels="wheels: $(find .whl -name '*.whl' | wc -l) installed into /tmp/site"
fi

# 2. the machine
cpu=$(lscpu | sed -n 's/^Model name:[[:space:]]*//p' | head -n 1)
cores=$(nproc)
if [ "$DEVICE" = cuda ]; then
  gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader | head -n 1)
  [ -n "$gpu" ] || { echo "eval_gpu: DEVICE=cuda but nvidia-smi names no GPU (DEVICE=cpu for the CPU)" >&2; exit 1; }
  tag="[GPU $gpu; CPU $cpu, $cores cores]"
else
  tag="[no GPU; CPU $cpu, $cores cores]"
fi

# Each line the measurements print, named by the machine, to the terminal and $OUT/result.log.
tagged() { awk -v tag="$tag" '{ print tag, $0; fflush() }' | tee -a "$OUT/result.log"; }
# Runs "$@" under timeout, its output tagged; says how it ended and how long it took.
measure() {
  local limit=$1 name=$2 tic=$SECONDS
  shift 2
  echo "== $name" | tagged
  timeout -k 10 "$limit" "$@" 2>&1 | tagged
  local rc=${PIPESTATUS[0]}
  case $rc in
    0) echo "== $name: done in $((SECONDS - tic)) s" | tagged ;;
    124) echo "== $name: stopped after the ${limit} s limit" | tagged ;;
    *) echo "== $name: exit status $rc after $((SECONDS - tic)) s" | tagged ;;
  esac
  return "$rc"
}

{
  echo "$wheels"
  [ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  echo "CPU: $cpu ($cores cores); Python $py_version ($PYTHON)"
  "$PYTHON" -c 'import torch; print(f"torch {torch.__version__}, CUDA available: {torch.cuda.is_available()}")'
} 2>&1 | tagged

# 3. the drive
bag=${1:-}
if [ -z "$bag" ]; then
  bag=$WORK/drive
  measure "$render_s" "citysim: $FRAMES frames, six 1600x900 JPEGs a frame, $cores processes" \
    "$PYTHON" -m citysim.cli --frames "$FRAMES" --image-size 1600x900 --seed 7 --out "$bag" --workers "$cores" \
    --no-progress --overwrite || exit 1
fi
echo "bag: $bag ($(du -sh "$bag" | cut -f1))" | tagged

# 4. retrieval only at the released size, then lcpr_eval with verification on
# shellcheck disable=SC2086  # BATCHES is a list of numbers
measure "$throughput_s" "retrieval only: eval_throughput.py --device $DEVICE --weights seeded --batches $BATCHES" \
  "$PYTHON" benchmarks/tools/eval_throughput.py "$bag" --device "$DEVICE" --weights seeded --batches $BATCHES
measure "$eval_s" "with verification: lcpr_eval --device $DEVICE --workers $WORKERS --no-scan-context (bundled weights)" \
  "$PYTHON" -m lcpr_ros.evaluate "$bag" --device "$DEVICE" --workers "$WORKERS" --no-scan-context --quiet \
  --out "$WORK/eval"
[ -f "$WORK/eval/report.json" ] && cp "$WORK/eval/report.json" "$OUT/lcpr_eval_report.json"

# the tables' rows and lcpr_eval's throughput with its stages, read whole before the log grows
summary=$(sed -e 's/^\[[^]]*\] //' "$OUT/result.log" \
  | awk '/^\| seeded \|/ || /^throughput:/ { print; keep = /^throughput:/; next } keep { print } { keep = 0 }')
printf '== summary\n%s\n' "$summary" | tagged
echo "total: $((SECONDS - start)) s" | tagged

#!/usr/bin/env bash
# Why VSeq2PC training trailed the network-free feature match, and what fixes it: short stage-2 runs
# (1 stage-1 epoch + 4 joint epochs of 3520 queries, the same budget each) on the six training drives
# of benchmarks/recipes/vseq2pc_train_synth.sh, compared by Recall@1 on the validation drive (seed 23) only. The held-out
# drive (seed 7) is not read here. About 9 minutes per variant on 2 idle cores (STUDY_ALL=1 adds a fifth).
#
#   bash benchmarks/studies/vseq2pc_loss_study.sh [OUT]   (default OUT=out/vseq2pc; the caches of step 1 of
#                                                   benchmarks/recipes/vseq2pc_train_synth.sh must be there)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=${1:-out/vseq2pc}
TRAIN=("$OUT"/train_seed{5,11,13,17,19,29}.npz)
COMMON=(--cache "${TRAIN[@]}" --val-cache "$OUT/val_seed23.npz" --pretrain-epochs 1 --epochs 4 --batch 32
        --queries-per-epoch 3520 --seq-base-lr 8e-3 --seq-warmup-epochs 0.5 --select recall_at_1 --no-progress)

run() {  # name, extra options
  local name=$1; shift
  [ -n "${SUMMARY_ONLY:-}" ] && return   # SUMMARY_ONLY=1: the table and figure of the runs already there
  [ -f "$OUT/study_$name/history.json" ] && grep -q '"epoch": 4' "$OUT/study_$name/history.json" && return
  echo "== $name: $*"
  $PY -m lcpr_offline.vseq2pc_train "${COMMON[@]}" --out "$OUT/study_$name" "$@"
}
run release --negatives 1                                          # the release's loss (bundled weights' recipe)
run mixed_bn --negatives 1 --mixed-batch-norm                      # batch norm as eval mode sees it
run mixed_bn_ranking --negatives 1 --mixed-batch-norm --ranking-weight 1   # + the ranking term
run ranking --negatives 1 --ranking-weight 1                       # the ranking term alone
[ -n "${STUDY_ALL:-}" ] && run ranking_hard --negatives 2 --mixed-batch-norm --ranking-weight 1 \
    --negative-max-radius 60                                       # + negatives from 20..60 m

$PY - "$OUT" <<'PY'
import json, sys
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

out = Path(sys.argv[1])
fig = Figure(figsize=(9, 3.6), dpi=100)
FigureCanvasAgg(fig)
axes = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
print(f"{'variant':<18} " + " ".join(f"R@1 ep{e}" for e in range(1, 5)) + "   best   max F1 (1:100) per epoch")
for run in ("release", "mixed_bn", "mixed_bn_ranking", "ranking", "ranking_hard"):
    path = out / f"study_{run}" / "history.json"
    if not path.is_file():
        continue
    rows = [h for h in json.loads(path.read_text())["history"] if h["stage"] == 2]
    r1 = [h.get("val_recall_at_1") or 0.0 for h in rows]
    f1 = [h.get("val_protocol_max_f1") or 0.0 for h in rows]
    print(f"{run:<18} " + " ".join(f"{r:7.3f}" for r in r1) + f"   {max(r1):.3f}  " + " ".join(f"{f:.3f}" for f in f1))
    epochs = [h["epoch"] for h in rows]
    axes[0].plot(epochs, r1, "o-", label=run)
    axes[1].plot(epochs, f1, "o-", label=run)
for ax, what in zip(axes, ("Recall@1 (loop queries)", "max F1 (pairs 1:100)")):
    ax.set(xlabel="stage-2 epoch", ylabel=what, title=f"validation drive: {what}", ylim=(0, 1))
    ax.grid(alpha=0.3)
axes[0].legend()
fig.tight_layout()
fig.savefig(out / "loss_study.png")
print(f"wrote {out / 'loss_study.png'}")
PY

"""``vseq2pc_train``: the command line of :func:`lcpr_core.vseq2pc.training.train.train`."""
from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Sequence

from lcpr_core.vseq2pc.pairs import (
    TrainPairConfig,
)
from lcpr_core.vseq2pc.training.config import SELECT_METRICS, TrainConfig
from lcpr_core.vseq2pc.training.train import train

log = logging.getLogger("lcpr_core.vseq2pc.training")

def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig(caches=("-",), out="")
    p = argparse.ArgumentParser(prog="vseq2pc_train", description="Train VSeq2PC on a feature cache "
                                "(vseq2pc_cache): stage 1 pretrains the sequence model, stage 2 trains both.")
    p.add_argument("--cache", required=True, nargs="+", help="training feature cache(s) (.npz), one per drive")
    p.add_argument("--out", required=True, help="output folder (weights, train_state.pt, history.json, curves.png)")
    p.add_argument("--val-cache", default=None, help="validation cache (default: the last --val-fraction of --cache)")
    p.add_argument("--val-fraction", type=float, default=d.val_fraction)
    p.add_argument("--pretrain-epochs", type=int, default=d.pretrain_epochs, help="stage 1 epochs")
    p.add_argument("--epochs", type=int, default=d.epochs, help="stage 2 epochs")
    p.add_argument("--batch", type=int, default=d.batch, help="query sequences per step")
    p.add_argument("--queries-per-epoch", type=int, default=None, help="subsample the queries of each epoch")
    p.add_argument("--seq-base-lr", type=float, default=d.seq_base_lr, help="AdamW base lr (x batch / 256)")
    p.add_argument("--seq-warmup-epochs", type=float, default=d.seq_warmup_epochs)
    p.add_argument("--desc-lr", type=float, default=d.desc_lr, help="Adam lr of the descriptor model")
    p.add_argument("--negatives", type=int, default=d.pairs.negatives, help="negatives (> 20 m) per positive")
    p.add_argument("--revisit-fraction", type=float, default=d.pairs.revisit_fraction,
                   help="share of positives taken from another pass when there is one")
    p.add_argument("--negative-max-radius", type=float, default=d.pairs.negative_max_radius,
                   help="draw negatives from 20 m..this radius of the query when it has any there (hard negatives)")
    p.add_argument("--mixed-batch-norm", action=argparse.BooleanOptionalAction, default=d.mixed_batch_norm,
                   help="scans and sequences pass the shared tower together in training, so its batch norm uses "
                        "the statistics eval mode uses (default off: the release's separate passes)")
    p.add_argument("--reconstruction-weight", type=float, default=d.reconstruction_weight,
                   help="keep stage 1's reconstruction MSE in stage 2 with this weight (0 = the release: F_seq may "
                        "then collapse to 0 and the sequence be ignored)")
    p.add_argument("--ranking-weight", type=float, default=d.ranking_weight,
                   help="weight of the ranking term (positives above negatives, softmax); 0 = the release's loss")
    p.add_argument("--select", choices=SELECT_METRICS, default=d.select,
                   help="what picks best_*.pth: the validation pairs' max F1, or Recall@1 on --val-cache")
    p.add_argument("--in-batch", action=argparse.BooleanOptionalAction, default=d.in_batch,
                   help="score each query against every scan sampled for the batch (default), or only its own")
    p.add_argument("--straight-through-clamp", action=argparse.BooleanOptionalAction,
                   default=d.straight_through_clamp,
                   help="let gradients pass the sequence model's [0, 1] output clamp (default), or not (the release)")
    p.add_argument("--init-sequence", default=None, help="start from these sequence weights (released or ours)")
    p.add_argument("--init-descriptor", default=None, help="start from these descriptor weights")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        config = TrainConfig(
            caches=tuple(args.cache), out=args.out, val_cache=args.val_cache, val_fraction=args.val_fraction,
            pretrain_epochs=args.pretrain_epochs, epochs=args.epochs, batch=args.batch,
            queries_per_epoch=args.queries_per_epoch, seq_base_lr=args.seq_base_lr,
            seq_warmup_epochs=args.seq_warmup_epochs, desc_lr=args.desc_lr,
            in_batch=args.in_batch, straight_through_clamp=args.straight_through_clamp,
            pairs=TrainPairConfig(negatives=args.negatives, revisit_fraction=args.revisit_fraction,
                                  negative_max_radius=args.negative_max_radius),
            ranking_weight=args.ranking_weight, reconstruction_weight=args.reconstruction_weight,
            select=args.select, mixed_batch_norm=args.mixed_batch_norm,
            seed=args.seed, threads=args.threads, progress=not args.no_progress, resume=args.resume,
            init_sequence=args.init_sequence, init_descriptor=args.init_descriptor,
        )
        start = time.perf_counter()
        run = train(config)
    except (ValueError, OSError) as err:
        print(f"vseq2pc_train: error: {err}", file=sys.stderr)
        return 2
    print(f"done in {time.perf_counter() - start:.0f} s; weights in {os.fspath(config.out)} "
          f"(best validation {'max F1' if config.select == 'max_f1' else 'Recall@1'} {run.best_f1:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``lcpr_train``: train LCPR on rosbag2 drives (synthetic or converted nuScenes) with triplet loss.

    lcpr_train BAG [BAG ...] --out DIR [--preset cpu|cpu_large|released] [--epochs N] [--lr LR] ...
    lcpr_train BAG ... --out DIR --resume --epochs 20      # continue from DIR/last.pth
    lcpr_train --export DIR/best.pth weights/lcpr_synth_narrow.pth   # small float16 copy
    lcpr_train BAG ... --whiten DIR/best.pth DIR/whitened.pth        # descriptor whitening fitted on BAGs
    lcpr_train --turn-average on DIR/whitened.pth DIR/turned.pth     # descriptors averaged over the 6 turns
    lcpr_train BAG ... --out DIR --preset released --device cuda --amp bf16 --time-budget 3600   # a GPU
    lcpr_train BAG ... --out DIR --init weights/lcpr_synth_narrow.pth --lr 3e-5   # fine-tune on your drives

Frames are preprocessed once into DIR/cache (memory-mapped uint8 images, float16 range
images); the split, mining and loss follow the paper (positives <= 9 m, negatives >= 18 m,
closest positive, 6 negatives inside the margin, m = 0.5, Adam with step decay). The paper's
learning rate (1e-5, x0.8 every 10 epochs) suits the released network on a GPU; short CPU
runs of the narrow preset need a higher one (e.g. --lr 3e-4).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from lcpr_core.errors import InvalidValueError, LcprError
from lcpr_core.lcpr.preprocess import PRESETS as LIDAR_PRESETS
from lcpr_core.lcpr.training.augment import AugmentConfig
from lcpr_core.lcpr.training.config import (
    AMP_MODES,
    NEGATIVE_RULES,
    PRESETS,
    MiningConfig,
    OptimConfig,
    SplitConfig,
    TrainConfig,
    checkpoint_inputs,
    input_preset,
)
from lcpr_core.lcpr.training.dataset import TrainingData
from lcpr_core.lcpr.training.train import Trainer, export_weights
from lcpr_core.lcpr.training.whiten import whiten_checkpoint
from lcpr_core.lcpr.turn_average import write_turn_average
from lcpr_core.lcpr.whitening import DEFAULT_DIMS, DEFAULT_POWER

from .lcpr_cache import build_cache


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lcpr_train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="*", type=Path, help="rosbag2 folders with cameras, LiDAR and odometry")
    p.add_argument("--out", type=Path, default=Path("out/train"), help="output folder (default out/train)")
    p.add_argument("--cache", type=Path, default=None, help="preprocessed-sample folder (default OUT/cache)")
    p.add_argument("--rebuild-cache", action="store_true", help="preprocess again even if the cache is up to date")
    p.add_argument("--cache-workers", type=int, default=1,
                   help="bags preprocessed at a time, each in its own process (default 1)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pth (epochs count on)")
    p.add_argument("--export", nargs=2, type=Path, metavar=("CHECKPOINT", "TARGET"), default=None,
                   help="write a small copy of CHECKPOINT (no optimizer state, float16) to TARGET and exit")
    p.add_argument("--export-fp32", action="store_true", help="with --export: keep float32 tensors")
    p.add_argument("--whiten", nargs=2, type=Path, metavar=("CHECKPOINT", "TARGET"), default=None,
                   help="describe every frame of BAGS with CHECKPOINT, fit a PCA whitening of its descriptors and "
                        "write CHECKPOINT with it to TARGET, then exit (give the training bags, never test ones)")
    p.add_argument("--whiten-power", type=float, default=DEFAULT_POWER,
                   help=f"with --whiten: each direction scaled by eigenvalue ** -POWER (default {DEFAULT_POWER})")
    p.add_argument("--whiten-dims", type=int, default=DEFAULT_DIMS,
                   help=f"with --whiten: principal directions kept (default {DEFAULT_DIMS})")
    p.add_argument("--turn-average", nargs=3, metavar=("on|off", "CHECKPOINT", "TARGET"), default=None,
                   help="write CHECKPOINT to TARGET asking (on) or not (off) for descriptors averaged over the six "
                        "camera-slot turns (six network passes per frame; lcpr_core.lcpr.turn_average), then exit")
    g = p.add_argument_group("model and inputs")
    g.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="cpu: 64x192 images, 16x288 ranges, width 0.25; cpu_large: 128x352, 32x528, 0.5; "
                        "released: 256x704, 32x1056, 1.0 (GPU) (default cpu, or with --init the checkpoint's)")
    g.add_argument("--width", type=float, default=None, help="channel multiplier (overrides the preset)")
    g.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="camera input size, multiples of 32 (overrides the preset)")
    g.add_argument("--range-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="range image size, multiples of 8 (overrides the preset)")
    g.add_argument("--lidar", choices=sorted(LIDAR_PRESETS), default=None,
                   help="range-image geometry preset (default nuscenes_lidar_top)")
    g.add_argument("--imagenet", default="", help="torchvision resnet18 state dict (local file; width 1.0 only)")
    g.add_argument("--init", default="", metavar="CHECKPOINT",
                   help="fine-tune: start from this checkpoint's network (a released checkpoint, a bundled or "
                        "exported file, a run's best.pth) with a fresh optimizer and epoch count; its sizes and "
                        "width are the defaults; whitening and turn averaging in it are not carried over (fit them "
                        "again on the result)")
    g.add_argument("--seed", type=int, default=0, help="initialisation and sampling seed (default 0)")
    g.add_argument("--lidar-only", action="store_true",
                   help="train for LiDAR-only robots: every camera slot empty in training, mining and validation "
                        "(as lcpr_node's lidar_only gives frames to the network); the weights are marked so, and "
                        "--whiten then fits their whitening on LiDAR-only frames too")
    g = p.add_argument_group("split and mining (paper defaults)")
    g.add_argument("--positive-radius", type=float, default=9.0, help="m (default 9)")
    g.add_argument("--negative-radius", type=float, default=18.0, help="m (default 18)")
    g.add_argument("--exclude-recent", type=float, default=30.0,
                   help="s: a revisit must be at least this much later (default 30)")
    g.add_argument("--fractions", type=float, nargs=3, metavar=("TRAIN", "VAL", "TEST"), default=(0.7, 0.1, 0.2),
                   help="shares of the queries (default 0.7 0.1 0.2)")
    g.add_argument("--negatives", type=int, default=6, help="negatives per query (default 6)")
    g.add_argument("--margin", type=float, default=0.5, help="triplet margin (default 0.5)")
    g.add_argument("--pool", type=int, default=64, help="random potential negatives examined per query (default 64)")
    g.add_argument("--negative-rule", choices=NEGATIVE_RULES, default="violating",
                   help="violating: d(q,n) < d(q,p) + m (default); absolute: d(q,n) < m (paper Eq. 7)")
    g = p.add_argument_group("optimisation")
    g.add_argument("--epochs", type=int, default=30, help="epochs in all, counting resumed ones (default 30)")
    g.add_argument("--lr", type=float, default=1e-5, help="Adam learning rate (default 1e-5, the paper's)")
    g.add_argument("--gamma", type=float, default=0.8, help="lr decay factor (default 0.8)")
    g.add_argument("--step-epochs", type=int, default=10, help="epochs between decays (default 10)")
    g.add_argument("--batch", type=int, default=4, help="queries per optimiser step (default 4)")
    g.add_argument("--queries-per-epoch", type=int, default=0, help="random training queries per epoch (0 = all)")
    g.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    g.add_argument("--device", default="cpu", help="torch device, e.g. cuda:0 (default cpu)")
    g.add_argument("--amp", choices=AMP_MODES, default="off",
                   help="off: float32; bf16: forward passes under bfloat16 autocast, for GPUs (default off)")
    g.add_argument("--time-budget", type=float, default=0.0, metavar="SECONDS",
                   help="begin no epoch that would end past SECONDS of training, judged by the last epoch's "
                        "time, and cut short one still running then (default 0: none; --epochs still caps the run)")
    g.add_argument("--eval-batch", type=int, default=16, help="samples per forward when describing (default 16)")
    g.add_argument("--quiet", action="store_true", help="no progress bars")
    g = p.add_argument_group("augmentation of the training inputs (off by default)")
    g.add_argument("--augment-yaw", type=float, default=0.0,
                   help="chance a sample is turned by whole camera slots, cloud with it (default 0)")
    g.add_argument("--augment-lighting", type=float, default=0.0,
                   help="chance its brightness is scaled by a factor in --brightness (default 0)")
    g.add_argument("--brightness", type=float, nargs=2, default=(0.3, 1.6), metavar=("LOW", "HIGH"),
                   help="range of the brightness factor (default 0.3 1.6)")
    g.add_argument("--augment-camera-drop", type=float, default=0.0,
                   help="chance one of its cameras is blacked out (default 0)")
    g.add_argument("--augment-lidar-occlusion", type=float, default=0.0,
                   help="chance a quarter of its range image is blacked out: a 90-degree sector, the top or the "
                        "bottom rows (default 0)")
    g.add_argument("--augment-lidar-fov", type=float, default=0.0,
                   help="chance its range image loses up to a quarter of its rows at the top and three eighths at the "
                        "bottom: a sensor whose beams span less than the range image's geometry (default 0)")
    g.add_argument("--augment-lidar-sparse", type=float, default=0.0,
                   help="chance it loses every second row (half the beams) or 10-50 %% of its returns (default 0)")
    return p


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    if args.preset is not None:
        inputs = input_preset(args.preset)
    elif args.init:  # the checkpoint's own inputs; a file without them is the released configuration
        inputs = checkpoint_inputs(args.init, default=PRESETS["released"])
    else:
        inputs = PRESETS["cpu"]
    overrides = {"width": args.width, "lidar": args.lidar,
                 "image_size": tuple(args.image_size) if args.image_size else None,
                 "range_size": tuple(args.range_size) if args.range_size else None}
    inputs = dataclasses.replace(inputs, **{k: v for k, v in overrides.items() if v is not None})
    return TrainConfig(
        inputs=inputs,
        split=SplitConfig(positive_radius=args.positive_radius, negative_radius=args.negative_radius,
                          exclude_recent_s=args.exclude_recent, fractions=tuple(args.fractions), seed=args.seed),
        mining=MiningConfig(negatives=args.negatives, margin=args.margin, pool=args.pool, rule=args.negative_rule),
        optim=OptimConfig(epochs=args.epochs, lr=args.lr, gamma=args.gamma, step_epochs=args.step_epochs,
                          queries_per_batch=args.batch, queries_per_epoch=args.queries_per_epoch,
                          time_budget_s=args.time_budget),
        seed=args.seed, imagenet=args.imagenet, init=args.init, threads=args.threads, eval_batch=args.eval_batch,
        device=args.device, amp=args.amp,
        augment=AugmentConfig(yaw=args.augment_yaw, lighting=args.augment_lighting,
                              brightness=tuple(args.brightness), camera_drop=args.augment_camera_drop,
                              lidar_occlusion=args.augment_lidar_occlusion, lidar_fov=args.augment_lidar_fov,
                              lidar_sparse=args.augment_lidar_sparse),
        lidar_only=args.lidar_only,
    )


def run(args: argparse.Namespace) -> int:
    if args.export:
        size = export_weights(*args.export, half=not args.export_fp32)
        print(f"exported {args.export[0]} -> {args.export[1]} ({size / 2**20:.2f} MiB, "
              f"{'float32' if args.export_fp32 else 'float16'})")
        return 0
    if args.turn_average:
        switch, checkpoint, target = args.turn_average
        if switch not in ("on", "off"):
            raise InvalidValueError(f"--turn-average {switch!r}; accepted: on, off")
        size = write_turn_average(checkpoint, target, on=switch == "on")
        print(f"turn averaging {switch}: {checkpoint} -> {target} ({size / 2**20:.2f} MiB)")
        return 0
    if not args.bags:
        raise InvalidValueError("no bags given; usage: lcpr_train BAG [BAG ...] --out DIR")
    if args.whiten:
        checkpoint, target = args.whiten
        samples = build_cache(args.bags, args.cache or args.out / "cache", inputs=checkpoint_inputs(checkpoint),
                              progress=not args.quiet)
        w = whiten_checkpoint(checkpoint, target, TrainingData.from_cache(samples), power=args.whiten_power,
                              dims=args.whiten_dims, batch=args.eval_batch, device=args.device,
                              progress=not args.quiet)
        print(f"whitening fitted on {w.samples} frames ({w.dims} of {w.dim} directions, power {w.power:g}): "
              f"{checkpoint} -> {target}")
        return 0
    config = config_from_args(args)
    start = time.perf_counter()
    cache = build_cache(args.bags, args.cache or args.out / "cache", inputs=config.inputs, progress=not args.quiet,
                        rebuild=args.rebuild_cache, workers=args.cache_workers)
    data = TrainingData.from_cache(cache, config.split, lidar_only=config.lidar_only)
    print(f"samples: {len(cache)} from {len(args.bags)} bag(s) (cache {cache.folder}, "
          f"built in {cache.meta.get('build_seconds', 0):.0f} s); split {data.split.summary()}", flush=True)
    inputs = config.inputs
    print(f"model: width {inputs.width:g}, {inputs.num_cameras} x {inputs.image_size[0]}x{inputs.image_size[1]} "
          f"images, {inputs.range_size[0]}x{inputs.range_size[1]} range image; Adam lr {config.optim.lr:g} "
          f"x{config.optim.gamma:g} every {config.optim.step_epochs} epochs; {config.mining.negatives} negatives, "
          f"margin {config.mining.margin:g} ({config.mining.rule})", flush=True)
    trainer = Trainer(data, config, args.out, progress=not args.quiet, echo=lambda s: print(s, flush=True))
    trainer.fit(resume=args.resume)
    test = trainer.test_recall()
    summary = {"test": test, "split": data.split.summary(), "wall_seconds": round(time.perf_counter() - start, 1)}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print("test queries (last epoch): " + ", ".join(f"{k} {100 * v:.1f}%" for k, v in test.items()))
    print(f"written: {args.out}/{{init,last,best}}.pth, history.json, curve.png, summary.json "
          f"({summary['wall_seconds']:.0f} s)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return run(args)
    except (LcprError, ValueError, OSError) as err:
        print(f"lcpr_train: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""Depth-scale fusion of the stacked frames (``PseudoCloudConfig.fuse``) against plain stacking, on one drive.

Per depth variant: the verified loops with the defaults and with the setting ``choose`` finds at the asked precision,
once with the frames stacked as they are and once with each frame's smooth depth-scale error corrected against the
other frames first (:func:`lcpr_core.vseq2pc.pseudo_cloud.fuse_scales`); and how far the pseudo-cloud lies from the
exact-depth one (median / mean / p90 of each point's distance to the nearest exact point, every 5th query)::

    nice .venv/bin/python benchmarks/tools/vseq2pc_verify_fusion.py out/vseq2pc_verify/val_seed43.npz \\
        --variants exact net5 net10 --out out/vseq2pc_verify/fusion_val.json
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main


def cloud_error(path: str, variant: str, *, fuse: bool, query_step: int, every: int = 5) -> dict[str, float]:
    """Median over queries of the median / mean / p90 distance (m) of the variant's pseudo-cloud points to the
    exact-depth pseudo-cloud of the same frames, and the p50 time (ms) of stacking."""
    import small_gicp

    from lcpr_core.vseq2pc.pseudo_cloud import PseudoCloudConfig, accumulate
    from lcpr_core.vseq2pc.sequence import sequence_table
    from lcpr_core.vseq2pc.verify_eval import load_drive

    exact, data = load_drive(path, "exact"), load_drive(path, variant)
    seqs = sequence_table(exact.poses[:, :3, 3], exact.valid)
    queries = np.flatnonzero(seqs[:, 0] >= 0)[::query_step][::every]
    cfg = PseudoCloudConfig(fuse=fuse)
    rows, times = [], []
    for f in queries.tolist():
        span = range(f, int(seqs[f, -1]) + 1)
        ref = accumulate([(exact.frame_clouds[i], exact.poses[i]) for i in span if exact.valid[i]],
                         query_pose=exact.poses[f])
        tic = time.perf_counter()
        pts = accumulate([(data.frame_clouds[i], data.poses[i]) for i in span if data.valid[i]],
                         query_pose=data.poses[f], config=cfg, lidar_T_cam=data.lidar_T_cam)
        times.append(time.perf_counter() - tic)
        _, sq = small_gicp.KdTree(ref, num_threads=1).batch_knn_search(pts, 1, num_threads=1)
        e = np.sqrt(np.asarray(sq)[:, 0])
        rows.append((np.median(e), np.mean(e), np.percentile(e, 90)))
    a = np.median(np.array(rows), axis=0)
    return {"median_m": float(a[0]), "mean_m": float(a[1]), "p90_m": float(a[2]),
            "stack_ms_p50": float(np.median(times) * 1e3), "queries": len(queries)}


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("drive", help="a drive file of benchmarks/tools/vseq2pc_verify_data.py")
    p.add_argument("--variants", nargs="+", default=["exact", "net5", "net10"])
    p.add_argument("--query-step", type=int, default=4)
    p.add_argument("--precision", type=float, default=1.0)
    p.add_argument("--setting", nargs=5, type=float, default=None,
                   metavar=("SUPPORT", "FITNESS", "COUNT", "M", "DEG"),
                   help="also report this setting (one chosen on the validation drive) as 'given'; on a held-out drive "
                        "'chosen' is then only what that drive itself would choose")
    p.add_argument("--fused-only", action="store_true", help="skip the plain stacking")
    p.add_argument("--out", default=None, help="JSON of the numbers")
    args = p.parse_args(argv)

    from lcpr_core.atomic import atomic_path
    from lcpr_core.vseq2pc.consistency import ConsistencyConfig
    from lcpr_core.vseq2pc.verify import SequenceVerifyConfig
    from lcpr_core.vseq2pc.verify_eval import (
        Setting,
        VerifyEvalConfig,
        bundled_net,
        choose,
        evaluate_verification,
        load_drive,
        summary,
    )

    config = VerifyEvalConfig(k=10, query_step=args.query_step)
    report: dict[str, Any] = {"drive": args.drive, "precision": args.precision, "variants": {}}
    for variant in args.variants:
        net = bundled_net(variant)
        data = load_drive(args.drive, variant)
        entry: dict[str, Any] = {}
        for fuse in (True,) if args.fused_only else (False, True):
            sweep_cfg = SequenceVerifyConfig(min_fitness=0.0)
            sweep_cfg = replace(sweep_cfg, pseudo=replace(sweep_cfg.pseudo, fuse=fuse))
            outcomes = evaluate_verification(data, net, verify=sweep_cfg, config=config)
            settings = {"default": Setting.of(SequenceVerifyConfig())}
            chosen = choose(outcomes, lidar_T_cam=data.lidar_T_cam, precision=args.precision)
            if chosen is not None:
                settings["chosen"] = chosen
            if args.setting is not None:
                sup, fit, count, max_m, max_deg = args.setting
                settings["given"] = Setting(int(sup), fit, ConsistencyConfig(count=int(count), max_m=max_m,
                                                                             max_deg=max_deg))
            s = summary(outcomes, settings, lidar_T_cam=data.lidar_T_cam)
            s["cloud"] = cloud_error(args.drive, variant, fuse=fuse, query_step=args.query_step) \
                if variant != "exact" else None
            entry["fused" if fuse else "stacked"] = s
            for name in settings:
                r = s[name]
                print(f"{variant:6} {'fused' if fuse else 'stacked':8} {name:8} {settings[name].label():32} "
                      f"published {r['published']:3d} wrong {r['wrong']:3d} recall {r['recall']:.2f} "
                      f"pose {r['pose_m_median'] if r['pose_m_median'] is None else round(r['pose_m_median'], 2)} m "
                      f"verify p50 {s['verify_ms_p50']:.0f} ms", flush=True)
            if s["cloud"] is not None:
                print(f"{variant:6} {'fused' if fuse else 'stacked':8} cloud vs exact: {s['cloud']}", flush=True)
        report["variants"][variant] = entry
    if args.out:
        with atomic_path(Path(args.out)) as tmp:
            tmp.write_text(json.dumps(report, indent=1, default=float) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``vseq2pc_eval``: VSeq2PC on a held-out feature cache as the paper evaluates it
(:mod:`lcpr_core.vseq2pc.evaluate`), or retrieval beside verified loops on drive files (``--verify``,
:mod:`lcpr_core.vseq2pc.verify_eval`)."""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

from lcpr_core.atomic import atomic_path
from lcpr_core.errors import InvalidValueError
from lcpr_core.pretrained import BUNDLED, VSEQ2PC_DEPTH_KINDS, describe_vseq2pc_weights, resolve_vseq2pc_weights
from lcpr_core.vseq2pc.dataset import FeatureCache, summary
from lcpr_core.vseq2pc.evaluate import EvalConfig, evaluate, evaluate_feature_match, plot_pr, table
from lcpr_core.vseq2pc.net import Vseq2pcNet
from lcpr_core.vseq2pc.pairs import POSITIVE_RADIUS


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vseq2pc_eval", description="Max F1 of (sequence, scan) pairs and Recall@N "
                                "of loop queries on a held-out feature cache (see vseq2pc_cache).")
    p.add_argument("--cache", default=None, help="held-out feature cache (.npz); required unless --verify")
    p.add_argument("--verify", nargs=2, default=None, metavar=("VALIDATION", "TEST"),
                   help="instead of a cache: retrieval alone beside verified loops on two drive files of "
                        "benchmarks/tools/vseq2pc_verify_data.py (the fitness threshold chosen on VALIDATION)")
    p.add_argument("--verify-never", default=None, metavar="DRIVE",
                   help="with --verify: a drive that never revisits its map; its published loops are counted")
    p.add_argument("--variants", nargs="+", default=["exact", "net10"],
                   help="with --verify: depth variants (exact, net5, net10, net20); default exact net10")
    p.add_argument("--precision", type=float, default=0.95,
                   help="with --verify: the validation precision the fitness threshold must keep")
    p.add_argument("--query-step", type=int, default=3, help="with --verify: every this-many sequence is a query")
    p.add_argument("--weights-dir", default=None, help="a vseq2pc_train output folder")
    p.add_argument("--which", choices=("final", "best"), default="final",
                   help="with --weights-dir: the last epoch's weights or the best validation max F1's")
    p.add_argument("--sequence-weights", default=None, help="sequence model file (released pickled module or ours)")
    p.add_argument("--descriptor-weights", default=None, help="descriptor model file ({'state_dict'} or plain)")
    p.add_argument("--name", default="trained", help="name of the weights' column")
    p.add_argument("--bundled-depth", choices=sorted(VSEQ2PC_DEPTH_KINDS), default="network",
                   help="without weight files: the bundled set for this kind of depth (default network)")
    p.add_argument("--untrained", "--seeded", action="store_true",
                   help="also evaluate the seeded untrained initialisation (random weights)")
    p.add_argument("--single-frame", action="store_true", help="also feed each network the query frame 4 times")
    p.add_argument("--sequence-lengths", type=int, nargs="+", default=[], metavar="L",
                   help="also evaluate each network on the first L frames of each sequence (1..3), the last repeated")
    p.add_argument("--feature-match", action="store_true",
                   help="also a reference without a network: camera feature vs scan windows, mean |difference|")
    p.add_argument("--init-seed", type=int, default=0, help="seed of the untrained initialisation")
    p.add_argument("--seed", type=int, default=0, help="seed of the negative-pair sample")
    p.add_argument("--min-frame-gap", type=int, default=50)
    p.add_argument("--negatives", type=int, default=100, help="negative pairs per positive")
    p.add_argument("--loop-radius", type=float, default=5.0)
    p.add_argument("--out", default=None, help="folder for eval.json and pr.png")
    return p


def _networks(args: argparse.Namespace) -> list[tuple[str, Vseq2pcNet]]:
    nets: list[tuple[str, Vseq2pcNet]] = []
    seq_file, desc_file = args.sequence_weights, args.descriptor_weights
    if args.weights_dir:
        prefix = "best_" if args.which == "best" else ""
        seq_file = seq_file or str(Path(args.weights_dir) / f"{prefix}sequence_model.pth")
        desc_file = desc_file or str(Path(args.weights_dir) / f"{prefix}descriptor_model.pth")
    if (seq_file is None) != (desc_file is None):
        raise InvalidValueError("give both --sequence-weights and --descriptor-weights (or --weights-dir)")
    if args.untrained:
        nets.append((f"untrained (seed {args.init_seed})", Vseq2pcNet.seeded(args.init_seed)))
    if seq_file is None:  # the bundled set for the depth asked for
        name = BUNDLED if args.bundled_depth == "network" else f"{BUNDLED}-exact"
        files = resolve_vseq2pc_weights(name, name)
        assert files is not None  # a bundled name always resolves to files (or raises)
        seq_file, desc_file = files
        print(f"vseq2pc_eval: {describe_vseq2pc_weights(files)}", file=sys.stderr)
        if args.name == "trained":
            args.name = name
    nets.append((args.name, Vseq2pcNet.from_files(sequence=seq_file, descriptor=desc_file)))
    return nets


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.verify is not None:
        from lcpr_core.vseq2pc.verify_eval import run  # registration (small_gicp) only where it is used
        try:
            return run(args)
        except (ValueError, OSError) as err:
            print(f"vseq2pc_eval: error: {err}", file=sys.stderr)
            return 2
    if args.cache is None:
        parser.error("give --cache (a feature cache) or --verify VALIDATION TEST (drive files)")
    try:
        config = EvalConfig(min_frame_gap=args.min_frame_gap, negatives_per_positive=args.negatives,
                            loop_radius=args.loop_radius, seed=args.seed)
        cache = FeatureCache.load(args.cache)
        results = [evaluate_feature_match(cache, config=config)] if args.feature_match else []
        for name, net in _networks(args):
            results.append(evaluate(net, cache, name=name, config=config))
            if args.single_frame:
                single = EvalConfig(**{**asdict(config), "single_frame": True})
                results.append(evaluate(net, cache, name=f"{name}, single frame", config=single))
            for length in args.sequence_lengths:
                shorter = EvalConfig(**{**asdict(config), "sequence_length": length})
                results.append(evaluate(net, cache, name=f"{name}, {length} frame(s)", config=shorter))
    except (ValueError, OSError) as err:
        print(f"vseq2pc_eval: error: {err}", file=sys.stderr)
        return 2
    info = summary(cache)
    print(f"{args.cache}: {info['frames']} frames, {info['complete_queries']} query sequences, path "
          f"{info['path_m']:.0f} m; pairs: < {POSITIVE_RADIUS:g} m and > {config.min_frame_gap} frames apart vs "
          f"> 20 m ({config.negatives_per_positive} per positive); loops: <= {config.loop_radius:g} m")
    print(table(results, n_values=config.n_values))
    if args.out:
        out = Path(args.out)
        report = {"cache": args.cache, "cache_summary": info, "config": asdict(config),
                  "methods": [r.to_dict() for r in results]}
        with atomic_path(out / "eval.json") as tmp:
            tmp.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        plot_pr(results, out / "pr.png", title=f"VSeq2PC pairs on {Path(args.cache).name}")
        print(f"wrote {out / 'eval.json'} and {out / 'pr.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``lcpr_eval``: offline evaluation of the loop detector on a rosbag2 (the command line; no DDS, no rclpy).

    lcpr_eval BAG [--weights FILE] [--precision P] [--runtime R] [--threads N] [--limit N] [--out DIR] ...
    lcpr_eval BAG --params-file config/lcpr.yaml [--weights FILE]      # exactly what lcpr_node would run
    lcpr_eval BAG --odometry kiss-icp                                  # KISS-ICP poses, then the back end's ATE
    lcpr_eval BAG --workers 4                                          # 4 verification processes (default: a core each)
    lcpr_eval BAG --verdicts-save V.json     # ... later, after a change to the verifier: --verdicts-compare V.json

Builds :class:`lcpr_offline.lcpr_evaluate.EvalOptions` from the flags, or from the node's parameter file
(:func:`lcpr_ros.params.settings_from_file`), and runs :func:`lcpr_offline.lcpr_evaluate.evaluate_bag`;
writes report.json, pr_curve.png, latency.png, trajectory.png (and posegraph.png; backend.png with
``--odometry kiss-icp``) into ``--out``. ``--verdicts-save FILE`` writes every candidate's verdict (decision,
reason, fitness, pose, by "query-match" keyframe ids); ``--verdicts-compare FILE`` compares this run's with such
a file, prints what differs and exits with status 1 when a decision or a reason differs or a pose moved more
than 1 mm / 0.01 deg (:mod:`lcpr_offline.verdicts`).
Protocols: see :mod:`lcpr_core.evaluation`.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path
from typing import Any

from lcpr_core.errors import LcprError
from lcpr_core.evaluation import summary_table, throughput_line
from lcpr_core.keyframes import KeyframeConfig
from lcpr_core.lcpr.describer import PRECISIONS, RUNTIMES, ModelConfig
from lcpr_core.lcpr.preprocess import PRESETS
from lcpr_core.lcpr.preprocess.cameras import DECODERS
from lcpr_core.pretrained import SEEDED, command_weights, describe_weights, resolve_weights
from lcpr_core.scan_context import ScanContextConfig
from lcpr_core.verification import SUBMAP_MODES, SubmapConfig, VerifierConfig
from lcpr_offline.lcpr_evaluate import (  # noqa: F401 - the evaluation's API, importable from the command's module too
    AUTO_BATCH,
    CUDA_BATCH,
    LIDAR_FOR_TOPICS,
    N_VALUES,
    ODOMETRY_SOURCES,
    OUTPUT_FILES,
    TOPIC_PRESETS,
    EvalOptions,
    base_T_lidar_of,
    evaluate_bag,
    write_outputs,
)
from lcpr_offline.verdicts import keep
from msg_tools.errors import MsgToolsError
from msg_tools.frames import Topics
from msg_tools.transforms import BASE_FRAME

from .params import NODE_DEFAULTS

#: What lcpr_node runs with no parameters set: the flags' defaults (one configuration source).
NODE = NODE_DEFAULTS


# ------------------------------------------------------------------------------- command line
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="lcpr_eval", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path, help="rosbag2 folder (sqlite3 or mcap) with cameras, LiDAR and odometry")
    p.add_argument("--out", type=Path, default=Path("out/eval"), help="output folder (default out/eval)")
    g = p.add_argument_group("model")
    g.add_argument("--weights", default="",
                   help="LCPR checkpoint or state dict (default: the bundled trained weights; 'seeded' = random)")
    g.add_argument("--seeded", action="store_true", help="random weights (testing only), as --weights seeded")
    g.add_argument("--imagenet", default="", help="torchvision resnet18 state dict, used without --weights")
    g.add_argument("--seed", type=int, default=0, help="random initialisation seed (default 0)")
    g.add_argument("--precision", choices=PRECISIONS, default=NODE.detector.model.precision,
                   help="inference path, as the node's model.precision (default %(default)s)")
    g.add_argument("--runtime", choices=RUNTIMES, default=NODE.detector.model.runtime,
                   help="what runs the exported graph, as the node's model.runtime (default %(default)s)")
    g.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's choice)")
    g.add_argument("--device", default=None,
                   help="torch device, e.g. cuda:0 (default cpu, or the parameter file's model.device)")
    g.add_argument("--batch", type=int, default=AUTO_BATCH,
                   help=f"frames whose keyframes are described in one network call, then matched in order as "
                        f"online (default: {CUDA_BATCH} on a GPU, one CUDA graph of that batch with the frames' JPEGs "
                        f"decoded together; 1 on the CPU)")
    g.add_argument("--decode", choices=DECODERS, default=NODE.detector.model.decode,
                   help="camera decoding, as the node's model.decode (default %(default)s: nvJPEG on a GPU, "
                        "reduced-size libjpeg-turbo on the CPU)")
    g.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="camera input size, multiples of 32 (default 256 704, the released model's)")
    g.add_argument("--lidar", choices=sorted(PRESETS), default=None,
                   help="range-image preset (default: by --topics, nuscenes_lidar_top or kitti_hdl64e)")
    g = p.add_argument_group("topics")
    g.add_argument("--topics", choices=sorted(TOPIC_PRESETS), default="nuscenes",
                   help="topic preset (default nuscenes; scans: /points and /odom as msg_tools_scans2bag writes them)")
    g.add_argument("--camera-topics", nargs="+", default=None, metavar="TOPIC", help="camera topics, in rig order")
    g.add_argument("--lidar-only", action="store_true",
                   help="read no cameras: every frame is described with all camera slots empty (a LiDAR-only "
                        "vehicle; --topics scans implies it)")
    g.add_argument("--lidar-topic", default=None, help="PointCloud2 topic")
    g.add_argument("--odom-topic", default=None, help="nav_msgs/Odometry topic (ground truth)")
    g.add_argument("--slop", type=float, default=NODE.node.sync.slop,
                   help="max s between a cloud and its images, as the node's sync.slop (default %(default)s)")
    g = p.add_argument_group("detection and evaluation")
    g.add_argument("--max-distance", type=float, default=NODE.detector.match.max_distance,
                   help="LCPR descriptor distance under which a loop is accepted, as the node's match.max_distance "
                        "(reported and drawn; default %(default)s)")
    g.add_argument("--sc-max-distance", type=float, default=None,
                   help="Scan Context distance (0..1) under which a loop is accepted (default: its max-F1 threshold)")
    g.add_argument("--radius", type=float, default=9.0,
                   help="m within which a match is correct (default 9, the paper's; 5 is stricter)")
    g.add_argument("--exclude-recent", type=float, default=NODE.detector.match.exclude_recent_s,
                   help="s of recent keyframes not matched, as match.exclude_recent_s (default %(default)s)")
    g.add_argument("--keyframe-interval", type=float, default=NODE.detector.keyframe.min_interval,
                   help="min s between keyframes, as keyframe.min_interval (default %(default)s)")
    g.add_argument("--keyframe-distance", type=float, default=NODE.detector.keyframe.min_distance,
                   help="min m travelled between keyframes, as keyframe.min_distance (default %(default)s: off)")
    g.add_argument("--split-offset", type=float, default=None,
                   help="s after the first keyframe where the database/query split lies (default: first real revisit)")
    g.add_argument("--limit", type=int, default=0, help="process at most N frames (default 0: all)")
    g.add_argument("--warmup", type=int, default=5, help="keyframes left out of latency statistics (default 5)")
    g.add_argument("--no-scan-context", action="store_true", help="skip the Scan Context baseline")
    g.add_argument("--no-verify", action="store_true",
                   help="no geometric verification against the LiDAR (retrieval only: no verified rows, no pose graph)")
    g.add_argument("--submap", choices=SUBMAP_MODES, default=None,
                   help="verify local submaps (keyframes stitched by the odometry), as submap.mode "
                        f"(default {NODE.detector.submap.mode})")
    g.add_argument("--base-frame", default=BASE_FRAME,
                   help="odometry child frame; base_T_lidar is the /tf_static transform from it to the cloud frame "
                        f"(default {BASE_FRAME}; identity when the bag has none)")
    g.add_argument("--drift-seed", type=int, default=0,
                   help="seed of the pose-graph proof's odometry drift (default 0)")
    g.add_argument("--lidar-height", type=float, default=2.0, help="m added to z by Scan Context (default 2.0)")
    g.add_argument("--odometry", choices=ODOMETRY_SOURCES, default="bag",
                   help="the detector's poses: the bag's odometry (default), or kiss-icp run on the bag's clouds "
                        "(the odometry extra), whose drift the back end then corrects with the verified loops: ATE "
                        "before and after against the bag's odometry, and backend.png")
    g.add_argument("--workers", type=int, default=None,
                   help="verification worker processes, running behind the network and the map search (the same "
                        "verdicts as the node's immediate verification; a --params-file's verify.processes is "
                        "the node's, not the evaluation's); 0 = in this process, each keyframe as it is stored "
                        "(default: one per core this process may run on)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.add_argument("--verdicts-save", type=Path, default=None, metavar="FILE",
                   help="write every candidate's verification verdict to this JSON file")
    g.add_argument("--verdicts-compare", type=Path, default=None, metavar="FILE",
                   help="compare every candidate's verdict with a --verdicts-save file (exit 1 when they differ)")
    g = p.add_argument_group("one configuration with the node")
    g.add_argument("--params-file", type=Path, default=None,
                   help="a node parameter file (e.g. config/lcpr.yaml): model, keyframing, matching, verification, "
                        "sync slop and topics as lcpr_node would run them; --weights, --imagenet, --seed, "
                        "--threads, --device and --odom-topic still apply, "
                        "the flags of those settings may not be given")
    return p.parse_args(argv)


#: Flags whose settings a --params-file gives (dest, default): giving both would leave it unclear which ran.
_FILE_SETTINGS = (("image_size", None), ("lidar", None), ("camera_topics", None), ("lidar_topic", None),
                  ("slop", NODE.node.sync.slop), ("max_distance", NODE.detector.match.max_distance),
                  ("exclude_recent", NODE.detector.match.exclude_recent_s),
                  ("keyframe_interval", NODE.detector.keyframe.min_interval),
                  ("keyframe_distance", NODE.detector.keyframe.min_distance),
                  ("precision", NODE.detector.model.precision), ("runtime", NODE.detector.model.runtime),
                  ("decode", NODE.detector.model.decode), ("submap", None))


def options_from_params_file(args: argparse.Namespace) -> EvalOptions:
    """What lcpr_node would run with ``args.params_file``, plus the evaluation's own options."""
    from .params import settings_from_file

    clash = [f"--{dest.replace('_', '-')}" for dest, default in _FILE_SETTINGS if getattr(args, dest) != default]
    if clash:
        raise ValueError(f"{', '.join(clash)} and --params-file {args.params_file} both set what the node runs; "
                         "give the value in the parameter file")
    settings = settings_from_file(args.params_file)
    det, node = settings.detector, settings.node
    base = TOPIC_PRESETS[args.topics]
    topics = dataclasses.replace(base, cameras=tuple(node.camera_topics), camera_info=(), depth=(), labels=(),
                                 lidar=node.lidar_topic, odom=args.odom_topic or node.odom_topic or base.odom)
    overrides = {k: getattr(args, k) for k in ("weights", "imagenet", "threads", "device") if getattr(args, k)}
    if args.seeded:
        overrides["weights"] = SEEDED
    if args.seed:
        overrides["seed"] = args.seed
    if args.lidar_only:
        topics = _without_cameras(topics)
    return EvalOptions(
        topics=topics, model=dataclasses.replace(det.model, **overrides), keyframe=det.keyframe,
        exclude_recent_s=det.match.exclude_recent_s, max_distance=det.match.max_distance, slop=node.sync.slop,
        verify=dataclasses.replace(det.verify, enabled=det.verify.enabled and not args.no_verify),
        submap=det.submap, **_evaluation_options(args),
    )


def _evaluation_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options that belong to the evaluation, not to what the node runs (the same with or without a
    parameter file)."""
    return dict(radius=args.radius,
                scan_context=None if args.no_scan_context else ScanContextConfig(lidar_height=args.lidar_height),
                sc_max_distance=args.sc_max_distance, limit=args.limit, warmup=args.warmup,
                split_offset=args.split_offset, base_frame=args.base_frame, drift_seed=args.drift_seed,
                batch=args.batch, lidar_only=args.lidar_only or args.topics == "scans",
                odometry=args.odometry, workers=args.workers)


def _without_cameras(topics: Topics) -> Topics:
    return dataclasses.replace(topics, cameras=(), camera_info=(), depth=(), labels=())


def options_from_args(args: argparse.Namespace) -> EvalOptions:
    if args.params_file is not None:
        return options_from_params_file(args)
    base = TOPIC_PRESETS[args.topics]
    topics = dataclasses.replace(
        base,
        cameras=tuple(args.camera_topics) if args.camera_topics else base.cameras,
        camera_info=() if args.camera_topics else base.camera_info,
        lidar=args.lidar_topic or base.lidar,
        odom=args.odom_topic or base.odom,
    )
    if args.camera_topics:  # depth/label topics belong to the preset's cameras
        topics = dataclasses.replace(topics, depth=(), labels=())
    if args.lidar_only:
        topics = _without_cameras(topics)
    model = ModelConfig(
        weights=SEEDED if args.seeded else command_weights(args.weights, imagenet=args.imagenet),
        imagenet=args.imagenet, seed=args.seed,
        num_cameras=len(topics.cameras) or ModelConfig().num_cameras,  # LiDAR only: the rig's slots, all empty
        image_size=tuple(args.image_size) if args.image_size else ModelConfig().image_size,
        lidar=args.lidar or LIDAR_FOR_TOPICS[args.topics], precision=args.precision, threads=args.threads,
        runtime=args.runtime, device=args.device or "cpu", decode=args.decode,
    )
    return EvalOptions(
        topics=topics, model=model,
        keyframe=KeyframeConfig(min_interval=args.keyframe_interval, min_distance=args.keyframe_distance),
        exclude_recent_s=args.exclude_recent, max_distance=args.max_distance, slop=args.slop,
        verify=VerifierConfig(enabled=not args.no_verify),
        submap=SubmapConfig(mode=args.submap) if args.submap else NODE.detector.submap, **_evaluation_options(args),
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        options = options_from_args(args)
        if (args.verdicts_save or args.verdicts_compare) and not options.verify.enabled:
            raise ValueError("--verdicts-save / --verdicts-compare need verification, which is off here (--no-verify "
                             "or the parameter file's verify.enabled: false)")
        if args.verdicts_compare is not None and not args.verdicts_compare.is_file():
            raise ValueError(f"--verdicts-compare {args.verdicts_compare}: no such file; accepted: a file written "
                             "by --verdicts-save")
        if not options.model.imagenet or options.model.weights:
            print(f"lcpr_eval: LCPR {describe_weights(resolve_weights(options.model.weights))}", file=sys.stderr)
        report = evaluate_bag(args.bag, options, progress=not args.quiet)
        paths = write_outputs(report, args.out)
    except (LcprError, MsgToolsError, ValueError, OSError) as err:
        print(f"lcpr_eval: {err}", file=sys.stderr)
        return 2
    print(f"\nlcpr_eval {args.bag} ({report.wall_time_s:.1f} s)")
    print(summary_table(report, n_values=N_VALUES))
    print(throughput_line(report))
    if report.backend is not None:
        print(f"back end: {report.backend.text()}")
    if not (report.settings["model"]["weights"] or report.settings["model"]["imagenet"]):
        print("note: LCPR ran with random weights (--seeded): its numbers are not those of a trained model")
    print("written: " + ", ".join(str(p) for p in paths))
    if report.verified is None or not (args.verdicts_save or args.verdicts_compare):
        return 0
    try:
        return keep(report.verified.verdicts, save_to=args.verdicts_save, compare_with=args.verdicts_compare,
                    same_run="run on the same bag with the same options", indent="")
    except (LcprError, ValueError, OSError) as err:
        print(f"lcpr_eval: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

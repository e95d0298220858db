"""Feature caches whose camera depth is what a monocular depth network gives, not the renderer's exact depth.

    python benchmarks/studies/vseq2pc_depth_range.py out/vseq2pc/train_seed5.npz ... --out out/vseq2pc_depth25
        [--max-depth 25] [--noise 0.1] [--seed 0]

VSeq2PC's paper estimates each image's dense depth with a network; the synthetic city's KITTI rig
publishes exact depth to any range, so one camera frame already shows nearly all of the LiDAR's
forward structure feature and a sequence has little to add. This rewrites the *camera* features
of existing caches (``vseq2pc_cache`` files) as a range-limited, noisy depth would have made them:

* every cell's range is scaled by (1 + noise x N(0, 1)), seeded per file;
* a class seen only beyond ``--max-depth`` along the optical axis (range x cos(sector angle)) is
  gone from that sector; road (the largest range) is cut back to that depth.

The LiDAR features, poses and stamps are copied unchanged. Written atomically, same names under --out.
"""
from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path

import numpy as np

from lcpr_core.errors import LcprError
from lcpr_core.vseq2pc.dataset import FeatureCache
from lcpr_core.vseq2pc.depth_range import coverage, limited_depth
from lcpr_core.vseq2pc.preprocess import MAX_RANGE


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("caches", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--max-depth", type=float, default=25.0, help="m along the optical axis (default 25)")
    p.add_argument("--noise", type=float, default=0.1, help="relative range noise, 1 sigma (default 0.1)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not 0 < args.max_depth <= MAX_RANGE or not 0 <= args.noise < 1:
        p.error(f"--max-depth {args.max_depth} must lie in (0, {MAX_RANGE}] and --noise {args.noise} in [0, 1)")
    args.out.mkdir(parents=True, exist_ok=True)
    for path in args.caches:
        try:
            cache = FeatureCache.load(path)
        except LcprError as err:
            p.error(str(err))
        rng = np.random.default_rng([args.seed, zlib.crc32(path.name.encode())])
        camera = limited_depth(cache.camera, max_depth=args.max_depth, noise=args.noise, rng=rng)
        FeatureCache(camera, cache.camera_valid, cache.lidar, cache.poses, cache.stamps,
                     f"{cache.source} (depth <= {args.max_depth:g} m, noise {args.noise:g})").save(args.out / path.name)
        kept = np.count_nonzero(camera) / max(int(np.count_nonzero(cache.camera)), 1)
        exact, limited = (coverage(c[cache.camera_valid], cache.lidar[cache.camera_valid])
                          for c in (cache.camera, camera))
        print(f"{path.name}: {len(cache)} frames, {100 * kept:.0f} % of the camera cells kept; of the LiDAR's "
              f"forward cells one camera frame holds {100 * exact[0]:.0f} % (median range error {exact[1]:.2f} m) "
              f"with exact depth, {100 * limited[0]:.0f} % ({limited[1]:.2f} m) now")
    return 0


if __name__ == "__main__":
    sys.exit(main())

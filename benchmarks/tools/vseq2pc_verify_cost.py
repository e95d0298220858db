"""What verifying one VSeq2PC query's 10 candidates costs: pseudo-cloud, preparation, registrations (median).

Reads a drive file of benchmarks/tools/vseq2pc_verify_data.py; for every ``--step``-th query sequence it
stacks the pseudo-cloud, prepares it and registers it against the 10 best scans of the retrieval (the
detector's code: :meth:`lcpr_core.vseq2pc.verify.SequenceVerifier.verify_all`). "cold": each scan's cloud
is prepared (normals, trees) for the query; "warm": from the verifier's cache, as in a running node whose
successive queries share most candidates. Prints medians with the CPU and the load (the machine may be shared).

    nice .venv/bin/python benchmarks/tools/vseq2pc_verify_cost.py out/vseq2pc_verify/test_seed7.npz --variant net10
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

import numpy as np

from lcpr_common.cli import tool_main


def cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("drive", help="a drive file of vseq2pc_verify_data.py")
    p.add_argument("--variant", default="net10")
    p.add_argument("--step", type=int, default=10, help="every this-many query sequence is timed")
    p.add_argument("--k", type=int, default=10)
    args = p.parse_args(argv)
    import torch

    from lcpr_core.vseq2pc.pseudo_cloud import accumulate
    from lcpr_core.vseq2pc.retrieval import ScanDatabase, SearchConfig
    from lcpr_core.vseq2pc.sequence import sequence_table
    from lcpr_core.vseq2pc.verify import SequenceVerifier, SequenceVerifyConfig
    from lcpr_core.vseq2pc.verify_eval import bundled_net, load_drive

    torch.set_num_threads(1)
    data = load_drive(args.drive, args.variant)
    net = bundled_net(args.variant)
    db = ScanDatabase(weights_id=net.weights_id)
    db.add(net.slice_descriptors(data.lidar), stamps=data.stamps, poses=data.poses)
    seqs = sequence_table(data.poses[:, :3, 3], data.valid)
    queries = np.flatnonzero(seqs[:, 0] >= 0)[:: args.step]
    d_seq = net.query_descriptors(data.camera[seqs[queries]])
    config = SequenceVerifyConfig()
    timings: dict[str, list[float]] = {"cold": [], "warm": []}
    for qi, frame in enumerate(queries.tolist()):
        found = db.search(d_seq[qi], net.descriptor, rows=frame,
                          config=SearchConfig(k=args.k, exclude_recent_s=None, exclude_recent_rows=50))[0]
        frames = [(data.frame_clouds[i], data.poses[i]) for i in range(frame, int(seqs[frame, -1]) + 1)
                  if data.valid[i] and len(data.frame_clouds[i])]
        if len(found) < args.k or not frames:
            continue
        verifier = SequenceVerifier(config)
        for kind in ("cold", "warm"):  # the second pass finds the scans prepared
            tic = time.perf_counter()
            query = verifier.prepare_query(accumulate(frames, query_pose=data.poses[frame], config=config.pseudo))
            verifier.verify_all(query, found, lambda m: data.scan_clouds[m.row], lidar_T_cam=data.lidar_T_cam)
            timings[kind].append(time.perf_counter() - tic)
    load = os.getloadavg()
    print(f"{cpu_name()}, {os.cpu_count()} logical CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; "
          f"small_gicp threads: {config.verifier.num_threads}")
    for kind, values in timings.items():
        ms = np.array(values) * 1e3
        print(f"{kind:5}: {len(ms)} queries x {args.k} candidates ({args.variant} depth): p50 {np.median(ms):.0f} ms, "
              f"p90 {np.percentile(ms, 90):.0f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

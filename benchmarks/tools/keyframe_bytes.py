"""Bytes of a peer keyframe on the wire (``~/keyframes``) and whether its cloud verifies as the local one does.

    python benchmarks/tools/keyframe_bytes.py [--frames 160] [--queries 30] [--candidates 5] [--sets city,livox]

Per keyframe, the whole record of :func:`lcpr_core.lcpr.peers.encode_peer_keyframe` (header, 256-float
descriptor, pose, cloud) in each cloud form:

- ``f32``, ``i16cm``, ``i16cm_dz``: the compact cloud as float32 metres, int16 centimetres, and int16
  centimetres delta-coded, split into byte planes and zlib-compressed (the wire forms; all three give the
  receiver the stored cloud bit for bit);
- ``i16_2cm_dz``: rounded to 2 cm first, then as ``i16cm_dz`` (lossy);
- ``voxel0.6_dz``: compacted with a 0.6 m voxel instead of ``verify.cloud.voxel`` (0.4), then ``i16cm_dz``
  (lossy).

Verdicts: for each of ``--queries`` revisiting keyframes, its ``--candidates`` earlier keyframes nearest in
position (at least 20 keyframes older) are verified against the query's local compact cloud, once with the
match's local cloud and once with the match's cloud as the receiver decodes it; a pair counts as identical
when the decision, the reason, the fitness and match_T_query are equal bit for bit.

Sets: ``city`` (the synthetic nuScenes-rig drive of city seed 3, a 360 deg 32-beam LiDAR, whose clouds reach
the 8192-point cap) and ``livox`` (../shared/data/livox_hku/walk_loop, a 70 deg Livox Avia). Prints the median,
mean and p90 bytes per keyframe, the encode / decode medians (ms) and the verdicts on this CPU.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main

TARGET_BYTES = 32 * 1024  # the average aimed at per keyframe
MIN_AGE = 20  # keyframes between a query and its candidates at least


@dataclass(frozen=True)
class Form:
    """One way a cloud travels: what the sender makes of the compact cloud and how the record encodes it."""

    name: str
    encoding: str  # lcpr_core.lcpr.peers.CLOUD_ENCODINGS
    lossy: Callable[[int], np.ndarray] | None = None  # keyframe -> the cloud sent instead of the compact one


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=160, help="frames of the city drive")
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--candidates", type=int, default=5)
    p.add_argument("--sets", default="city,livox", help="comma-separated: city, livox")
    args = p.parse_args(argv)
    sets = [s for s in args.sets.split(",") if s]
    unknown = set(sets) - {"city", "livox"}
    if unknown or not sets:
        raise SystemExit(f"--sets {args.sets!r}; accepted: city, livox (comma-separated)")

    from lcpr_core.timing import cpu_model

    print(f"CPU: {cpu_model()}")
    for name in sets:
        seq = _scans(name, args.frames)
        if seq is None:
            print(f"\n{name}: skipped (../shared/data/livox_hku/walk_loop not found)")
            continue
        _measure(name, seq, queries=args.queries, candidates=args.candidates)
    return 0


def _scans(name: str, frames: int) -> Any:
    if name == "city":
        from lcpr_offline.verification_pairs import SyntheticLidar

        return SyntheticLidar("nuscenes", 3, frames)
    from lcpr_common.shared_data import shared_path
    from msg_tools.convert.scan_folder import ScanFolder

    folder = shared_path("data", "livox_hku") / "walk_loop"
    return ScanFolder(folder) if folder.is_dir() else None


def _measure(name: str, seq: Any, *, queries: int, candidates: int) -> None:
    from tqdm import tqdm

    from lcpr_core.lcpr.peers import PeerKeyframe, decode_peer_keyframe, encode_peer_keyframe
    from lcpr_core.verification import GeometricVerifier, VerifierConfig
    from lcpr_core.verification.clouds import dequantise, quantise

    config = VerifierConfig(num_threads=1, processes=0)
    verifier = GeometricVerifier(config)
    coarse = GeometricVerifier(replace(config, cloud=replace(config.cloud, voxel=0.6)))
    n = len(seq.poses)
    compact = [verifier.compact(seq.points(i)) for i in tqdm(range(n), desc=f"{name}: compact clouds")]
    forms = [
        Form("f32", "f32"), Form("i16cm", "i16cm"), Form("i16cm_dz", "i16cm_dz"),
        Form("i16_2cm_dz", "i16cm_dz", lambda i: dequantise(quantise(np.round(compact[i] / 0.02) * 0.02))),
        Form("voxel0.6_dz", "i16cm_dz", lambda i: coarse.compact(seq.points(i))),
    ]
    rng = np.random.default_rng(0)
    descriptor = rng.normal(size=256).astype(np.float32)
    sent: dict[str, list[np.ndarray]] = {}
    for form in forms:
        sizes, enc_ms, dec_ms, clouds = [], [], [], []
        for i in range(n):
            cloud = compact[i] if form.lossy is None else form.lossy(i)
            kf = PeerKeyframe(stamp=float(i), session="peer", descriptor=descriptor, pose=seq.poses[i],
                              weights_id="0123456789abcdef", cloud=cloud)
            tic = time.perf_counter()
            data = encode_peer_keyframe(kf, encoding=form.encoding)
            enc_ms.append(1e3 * (time.perf_counter() - tic))
            tic = time.perf_counter()
            back = decode_peer_keyframe(data)
            dec_ms.append(1e3 * (time.perf_counter() - tic))
            sizes.append(len(data))
            assert back.cloud is not None
            clouds.append(back.cloud)
        sent[form.name] = clouds
        b = np.array(sizes, np.float64)
        print(f"{name} {form.name:12s} bytes/keyframe median {np.median(b) / 1024:6.1f} KiB, mean "
              f"{b.mean() / 1024:6.1f} KiB, p90 {np.percentile(b, 90) / 1024:6.1f} KiB "
              f"({'within' if b.mean() <= TARGET_BYTES else 'over'} 32 KiB on average); encode "
              f"{np.median(enc_ms):.2f} ms, decode {np.median(dec_ms):.2f} ms (medians)")
    points = np.array([len(c) for c in compact])
    print(f"{name}: {n} keyframes, compact cloud points median {int(np.median(points))}, max {points.max()}")

    positions = seq.poses[:, :3, 3]
    cases = []
    for q in range(MIN_AGE, n):
        d = np.linalg.norm(positions[: q - MIN_AGE] - positions[q], axis=1)
        if len(d) and d.min() < 3.0:  # a revisit
            cases.append((q, np.argsort(d)[:candidates].tolist()))
    cases = [cases[k] for k in np.linspace(0, len(cases) - 1, min(queries, len(cases))).round().astype(int)] \
        if cases else []
    pairs = [(q, m) for q, ms in cases for m in ms]
    local = {(q, m): verifier.verify(compact[q], compact[m]) for q, m in tqdm(pairs, desc=f"{name}: local")}
    accepted = sum(v.accepted for v in local.values())
    print(f"{name}: {len(pairs)} pairs ({len(cases)} revisiting queries x {candidates} nearest earlier keyframes), "
          f"{accepted} accepted with the local clouds")
    for form in forms:
        same_decision = same_all = accepted_here = 0
        for q, m in tqdm(pairs, desc=f"{name}: {form.name}", leave=False):
            v, w = local[(q, m)], verifier.verify(compact[q], sent[form.name][m])
            accepted_here += w.accepted
            same_decision += (v.accepted, v.reason) == (w.accepted, w.reason)
            same_all += ((v.accepted, v.reason, v.fitness) == (w.accepted, w.reason, w.fitness)
                         and np.array_equal(v.match_T_query, w.match_T_query))
        print(f"{name} {form.name:12s} verdicts: same decision and reason {same_decision}/{len(pairs)}, "
              f"identical (fitness, match_T_query bit for bit) {same_all}/{len(pairs)}, accepted {accepted_here}")


if __name__ == "__main__":
    sys.exit(main())

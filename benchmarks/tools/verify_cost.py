"""Cost of verifying one keyframe's candidates (the issue's "10 candidates <= 150 ms p50, 2 cores").

    python benchmarks/tools/verify_cost.py [--queries 30] [--candidates 10] [--frames 160] [--max-points N]
                                           [--workers 2] [--processes 2] [--set num_threads=2 ...]
                                           [--save VERDICTS.json] [--compare VERDICTS.json] [--profile]

A synthetic nuScenes-rig drive (city seed 3, 32-beam LiDAR, compact clouds capped at ``--max-points``).
For each revisiting keyframe, the ``--candidates`` earlier keyframes *nearest in position*
(at least 20 keyframes older) are verified: a harder mix than retrieval's top 10, since
near candidates are the ones that reach the fine stage. Per keyframe the time covers
preparing the query cloud and verifying every candidate; the candidates' clouds are
prepared beforehand (the node caches 64 of them), and ``uncached`` adds preparing them too.
``--workers N`` also verifies the cached candidates over N threads (:meth:`GeometricVerifier.verify_all`),
right after the same keyframe one by one (a fair comparison on a busy machine), and over ``--processes N``
worker processes (default: ``verify.processes``, the node's; 0 leaves them out;
:class:`~lcpr_core.verification.processes.VerifierProcesses`: each worker keeps its own prepared clouds, warmed by
the first pass); every verdict of any of them is
compared with the uncached pass's (they must be the same).
``--set NAME=VALUE`` overrides a numeric :class:`~lcpr_core.verification.VerifierConfig` field (to
compare settings back to back). Prints medians and p90 on this CPU: wall time and the CPU time (this process's
threads and the worker processes'; less sensitive to other jobs on a shared machine than the wall time).

``--save FILE`` writes every verdict (decision, reason, fitness, pose); ``--compare FILE`` checks this
run's verdicts against such a file, candidate for candidate (e.g. before and after a change to the
verifier), prints what differs and exits with status 1 when a decision or a reason differs or a pose
moved more than 1 mm / 0.01 deg (:mod:`lcpr_offline.verdicts`).

``--profile`` also prints where the time goes: per keyframe of the one-by-one pass, the wall and CPU time of
each stage (:data:`STAGES`), measured by wrapping the methods of the verifier instance for that pass only
(:class:`StageProfile`; the verifier's code is untouched and the verdicts are the same), and for the worker
processes what the parent can see: the pass's wall time against the workers' own verification and CPU time.

It also counts the accepted pairs whose pose is right (within 0.5 m / 3 deg of the drive's LiDAR poses) and
lists those accepted with a wrong pose: a candidate nearest in position may lie 5-20 m away, and accepting it is
no error only with its pose right.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.cli import tool_main

POSE_OK_M, POSE_OK_DEG = 0.5, 3.0  # an accepted pair's pose is right within these of the drive's poses
# --profile: each stage and the GeometricVerifier methods whose time it is charged; "other" is the rest of the pass
STAGE_METHODS: dict[str, tuple[str, ...]] = {
    "prepare (query)": ("prepare",),
    "starts (BEV / Scan Context yaw)": ("starts", "hypotheses"),
    "coarse GICP": ("_coarse",),
    "fine GICP": ("_fine",),
    "evidence + overlap": ("_evidence", "_overlap"),
    "ambiguity (its registrations included)": ("_alternative",),
    "free space": ("contradiction",),
    "judge + covariance": ("_judge", "_covariance"),
}
OTHER = "other"
STAGES: tuple[str, ...] = (*STAGE_METHODS, OTHER)
# stages that keep the time of the stages they call: the ambiguity test's extra starts and registrations are its cost
OWNS_NESTED = frozenset({"ambiguity (its registrations included)"})


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=160)
    p.add_argument("--queries", type=int, default=30)
    p.add_argument("--candidates", type=int, default=10)
    p.add_argument("--repeats", type=int, default=3, help="passes over the queries (the first one warms up)")
    p.add_argument("--max-points", type=int, default=None, help="compact cloud cap (default: CloudConfig's)")
    p.add_argument("--workers", type=int, default=1, help="threads verifying the cached candidates (default 1)")
    p.add_argument("--processes", type=int, default=None,
                   help="also time verification over this many worker processes (default: verify.processes, "
                        "the node's; 0: not)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a numeric VerifierConfig field, e.g. overlap_points=0 (repeatable)")
    p.add_argument("--save", type=Path, default=None, help="write every verdict to this JSON file")
    p.add_argument("--compare", type=Path, default=None, help="compare the verdicts with a --save file")
    p.add_argument("--profile", action="store_true",
                   help="also print each stage's share of the wall and CPU time (one by one; worker processes)")
    args = p.parse_args(argv)
    if args.workers < 1:
        raise SystemExit(f"--workers {args.workers}; accepted: an integer >= 1")
    if args.processes is not None and args.processes < 0:
        raise SystemExit(f"--processes {args.processes}; accepted: an integer >= 0")

    from concurrent.futures import ThreadPoolExecutor
    from dataclasses import replace

    from tqdm import tqdm

    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import GeometricVerifier, Verification, VerifierConfig
    from lcpr_core.verification.processes import CloudRef, VerifierProcesses
    from lcpr_offline import verdicts as verdict_file
    from lcpr_offline.verification_pairs import SyntheticLidar, synthetic_pairs

    seq = SyntheticLidar("nuscenes", 3, args.frames)
    true, _ = synthetic_pairs(seq, far_random=1, seed=3)
    overrides: dict[str, Any] = dict(_setting(item) for item in args.set)  # Any: fields of several types
    config = replace(VerifierConfig(), **overrides)
    if args.max_points is not None:
        config = replace(config, cloud=replace(config.cloud, max_points=args.max_points))
    verifier = GeometricVerifier(config)
    compact = [verifier.compact(seq.points(i)) for i in tqdm(range(len(seq)), desc="compact clouds")]
    positions = seq.poses[:, :3, 3]
    queries = np.unique(true[:, 0])[: args.queries]
    cases = []
    for q in queries:
        d = np.linalg.norm(positions[: max(q - 20, 0)] - positions[q], axis=1)
        cases.append((int(q), np.argsort(d)[: args.candidates].tolist()))
    if not cases or args.repeats < 2:
        raise SystemExit(f"--frames {args.frames} gives {len(cases)} revisiting keyframes and --repeats "
                         f"{args.repeats}; accepted: a drive with revisits (the default 160 frames) and >= 2 passes")
    prepared = {i: verifier.prepare(compact[i]) for c in cases for i in c[1]}
    timed: dict[str, tuple[list[float], list[float]]] = {"one by one": ([], [])}  # name: (wall, CPU) per keyframe
    if args.workers > 1:
        timed[f"over {args.workers} threads"] = ([], [])
    uncached, accepted = [], []
    verdicts: dict[tuple[int, int], Verification] = {}
    mismatches: list[str] = []
    pool = ThreadPoolExecutor(args.workers) if args.workers > 1 else None
    count = config.processes if args.processes is None else args.processes
    processes = VerifierProcesses(config, processes=count) if count > 0 else None
    if processes is not None:
        timed[f"over {count} processes"] = ([], [])
    ref = lambda i: CloudRef(i, lambda: compact[i])  # noqa: E731 - a keyframe's cloud by its index
    profile = StageProfile(verifier) if args.profile else None
    stage_times: list[tuple[dict[str, float], dict[str, float]]] = []  # per keyframe: (wall, CPU) by stage
    remote: list[tuple[float, float, float, float]] = []  # per keyframe: wall, workers' verification, their CPU, ours
    try:
        for _ in tqdm(range(args.repeats), desc="passes"):
            for q, candidates in cases:
                found: dict[str, list[Verification]] = {}
                for name, (wall, cpu_time) in timed.items():  # back to back on the same keyframe
                    tic, cpu = time.perf_counter(), time.process_time()
                    if processes is not None:  # the workers' CPU time counts too
                        cpu += processes.worker_cpu_seconds
                    if name.endswith("processes"):
                        assert processes is not None
                        workers_cpu, own_cpu = processes.worker_cpu_seconds, time.process_time()
                        answers = processes.verify([(ref(q), ref(m)) for m in candidates])
                        found[name] = [v for v in answers if isinstance(v, Verification)]
                        assert len(found[name]) == len(candidates), answers
                        remote.append((time.perf_counter() - tic, sum(v.seconds for v in found[name]),
                                       processes.worker_cpu_seconds - workers_cpu, time.process_time() - own_cpu))
                    else:
                        profiled = profile if name == "one by one" else None  # --profile times that pass
                        with profiled.measuring() if profiled is not None else nullcontext():
                            query = verifier.prepare(compact[q])
                            found[name] = verifier.verify_all(query, [prepared[m] for m in candidates],
                                                              pool=None if name == "one by one" else pool)
                        if profiled is not None:
                            stage_times.append(profiled.take())
                    wall.append(time.perf_counter() - tic)
                    cpu_time.append(time.process_time() - cpu + (processes.worker_cpu_seconds if processes else 0.0))
                accepted.append(sum(v.accepted for v in found["one by one"]))
                tic = time.perf_counter()
                query = verifier.prepare(compact[q])
                for k, m in enumerate(candidates):
                    alone = verifier.verify_prepared(query, verifier.prepare(compact[m]))
                    for name, vs in found.items():
                        mismatches += verdict_file.differences(f"{q}-{m} ({name} vs uncached)",
                                                               verdict_file.record(vs[k]), verdict_file.record(alone))
                    verdicts[q, m] = alone
                uncached.append(time.perf_counter() - tic)
        if processes is not None:
            peaks = [_peak_rss_mib(pid) for pid in processes.pids]
            print(f"worker processes: peak resident memory {', '.join(f'{m:.0f}' for m in peaks)} MiB")
    finally:
        if pool is not None:
            pool.shutdown()
        if processes is not None:
            processes.close()
    skip = len(cases)  # the warm-up pass
    ms = lambda xs: f"p50 {1e3 * np.median(xs[skip:]):.1f} ms, p90 {1e3 * np.percentile(xs[skip:], 90):.1f} ms"  # noqa: E731
    print(f"CPU: {cpu_model()}, verifier threads {verifier.config.num_threads}; {len(cases)} keyframes x "
          f"{args.candidates} candidates (accepted per keyframe: median {np.median(accepted):.0f})")
    for name, (wall, cpu_time) in timed.items():
        print(f"  verification per keyframe, candidate clouds cached, {name}: {ms(wall)} (CPU time {ms(cpu_time)})")
    print(f"  verification per keyframe, nothing cached, one by one: {ms(uncached)}")
    if profile is not None:
        print(_stage_table(stage_times[skip:], cpu_model(), verifier.config.num_threads,
                           [stage for stage, n in profile.calls.items() if n == 0]))
        if remote:
            print(_remote_summary(remote[skip:], count))
    right, wrong = _pose_check(verdicts, seq.poses)
    print(f"  accepted with the right pose (within {POSE_OK_M} m / {POSE_OK_DEG} deg of the drive's): {right}; "
          f"with a wrong pose: {len(wrong)}")
    for line in wrong:
        print("    " + line)
    records = {f"{q}-{m}": verdict_file.record(v) for (q, m), v in verdicts.items()}
    if args.save is not None:
        verdict_file.save(args.save, records)
        print(f"  verdicts written to {args.save}")
    if args.compare is not None:
        mismatches += verdict_file.compare(args.compare, records,
                                           same_run="run with the same --frames/--queries/--candidates")
    print(f"  verdicts compared: {len(mismatches)} differences")
    for line in mismatches[:20]:
        print("    " + line)
    return 1 if mismatches else 0


class StageProfile:
    """Exclusive wall and CPU time per stage (:data:`STAGES`) of one :class:`GeometricVerifier` instance's work.

    While :meth:`measuring`, the instance's methods named in :data:`STAGE_METHODS` are replaced by wrappers on
    the instance (the class and other instances are untouched; verdicts are the same). A stack of the active
    stages charges each interval to the innermost one (the overlap inside a coarse registration counts as
    evidence + overlap, not twice), except inside a stage of :data:`OWNS_NESTED`, which keeps what it calls;
    time outside every stage is "other". CPU time is this process's (``time.process_time``: the verifier's
    registration threads included; nothing else runs in it during the one-by-one pass).
    """

    def __init__(self, verifier: Any) -> None:
        self.verifier = verifier
        self.wall, self.cpu = dict.fromkeys(STAGES, 0.0), dict.fromkeys(STAGES, 0.0)
        self.calls = dict.fromkeys(STAGE_METHODS, 0)  # times each stage was entered, over all the keyframes
        self._stack: list[str] = []
        self._mark = (0.0, 0.0)

    @contextmanager
    def measuring(self) -> Iterator[None]:
        """Times the verifier's stages while the block runs (the block's time outside them counts as other)."""
        names = [(stage, name) for stage, methods in STAGE_METHODS.items() for name in methods]
        for stage, name in names:
            setattr(self.verifier, name, self._timed(stage, getattr(self.verifier, name)))
        self._stack.clear()
        self._mark = (time.perf_counter(), time.process_time())
        try:
            yield
        finally:
            self._charge()
            for _, name in names:
                delattr(self.verifier, name)  # the class's method again

    def take(self) -> tuple[dict[str, float], dict[str, float]]:
        """(wall, CPU) seconds by stage since the last take, and start again from zero."""
        out = (self.wall, self.cpu)
        self.wall, self.cpu = dict.fromkeys(STAGES, 0.0), dict.fromkeys(STAGES, 0.0)
        return out

    def _charge(self) -> None:
        """Charge the time since the last mark to the innermost active stage."""
        wall, cpu = time.perf_counter(), time.process_time()
        stage = self._stack[-1] if self._stack else OTHER
        self.wall[stage] += wall - self._mark[0]
        self.cpu[stage] += cpu - self._mark[1]
        self._mark = (wall, cpu)

    def _timed(self, stage: str, method: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._stack and self._stack[-1] in OWNS_NESTED:
                return method(*args, **kwargs)
            self.calls[stage] += 1
            self._charge()
            self._stack.append(stage)
            try:
                return method(*args, **kwargs)
            finally:
                self._charge()
                self._stack.pop()
        return timed


def _stage_table(times: list[tuple[dict[str, float], dict[str, float]]], cpu: str, threads: int,
                 unreached: list[str]) -> str:
    """--profile's table: per stage the median ms per keyframe and the share of the total over the keyframes,
    wall and CPU, as Markdown (the shares sum to 100 %; the medians need not sum to the total's median), and the
    stages never entered (``unreached``: a zero there is no measurement)."""
    walls = np.array([[w[s] for s in STAGES] for w, _ in times]) * 1e3  # keyframes x stages, ms
    cpus = np.array([[c[s] for s in STAGES] for _, c in times]) * 1e3
    lines = [f"where the time goes, one by one in one process ({cpu}, verifier threads {threads}; {len(times)} "
             "keyframes timed over the passes after the first; ms per keyframe: median; share: of their sum):",
             "| stage | wall ms | share of wall | CPU ms | share of CPU |", "|---|---|---|---|---|"]
    wall_share = 100.0 * walls.sum(axis=0) / max(walls.sum(), 1e-12)
    cpu_share = 100.0 * cpus.sum(axis=0) / max(cpus.sum(), 1e-12)
    for k, stage in enumerate(STAGES):
        lines.append(f"| {stage} | {np.median(walls[:, k]):.1f} | {wall_share[k]:.1f} % | "
                     f"{np.median(cpus[:, k]):.1f} | {cpu_share[k]:.1f} % |")
    lines.append(f"| total | {np.median(walls.sum(axis=1)):.1f} | 100 % | {np.median(cpus.sum(axis=1)):.1f} | 100 % |")
    if unreached:
        lines.append(f"never entered on this drive: {', '.join(unreached)}")
    lines.append("submap stitching: not exercised (360 deg clouds: submap mode auto verifies single scans); "
                 "caching: the candidates' clouds are prepared beforehand, as the node caches them")
    return "\n".join(lines)


def _remote_summary(remote: list[tuple[float, float, float, float]], processes: int) -> str:
    """--profile's line on the worker processes, from the parent: per keyframe (median ms) the pass's wall time,
    the workers' verification (the verdicts' own seconds, summed), their CPU time for the requests (verification and
    preparing the clouds they lack) and this process's CPU time (requests, pickling); the wall time not covered by
    the workers' CPU time shared evenly is moving data to and from them, pickling and waiting for the slower one."""
    wall, verify, worker_cpu, own_cpu = (1e3 * np.array(column) for column in zip(*remote, strict=True))
    rest = wall - worker_cpu / processes
    return (f"over {processes} worker processes (seen from the parent; ms per keyframe, median): wall "
            f"{np.median(wall):.1f}; in the workers, verification {np.median(verify):.1f} (the verdicts' seconds, "
            f"all workers) and CPU {np.median(worker_cpu):.1f} (verification and preparing the clouds they lack); "
            f"this process's CPU {np.median(own_cpu):.1f}; wall - workers' CPU / {processes}: {np.median(rest):.1f} "
            "(moving data to and from the workers, pickling, waiting for the slower one)")


def _pose_check(verdicts: dict[tuple[int, int], Any], poses: np.ndarray) -> tuple[int, list[str]]:
    """(accepted pairs whose pose is right, a line per accepted pair whose pose is wrong) against the drive's
    LiDAR poses (N x 4 x 4): a candidate may be any distance away, but an accepted one must have its pose."""
    from lcpr_offline.verification_pairs import pose_error

    right, wrong = 0, []
    for (q, m), v in sorted(verdicts.items()):
        if not v.accepted:
            continue
        err_m, err_deg = pose_error(v.match_T_query, np.linalg.inv(poses[m]) @ poses[q])
        if err_m <= POSE_OK_M and err_deg <= POSE_OK_DEG:
            right += 1
        else:
            apart = float(np.linalg.norm(poses[q, :3, 3] - poses[m, :3, 3]))
            wrong.append(f"{q}-{m}: {apart:.1f} m apart, pose off by {err_m:.2f} m / {err_deg:.1f} deg "
                         f"(fitness {v.fitness:.3f})")
    return right, wrong


def _peak_rss_mib(pid: int) -> float:
    """A process's peak resident memory (Linux /proc; NaN where it cannot be read)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _setting(item: str) -> tuple[str, int | float]:
    """"name=value" -> (name, int or float), or SystemExit naming the item and the accepted form."""
    name, sep, text = item.partition("=")
    try:
        value: int | float = int(text) if text.lstrip("-").isdigit() else float(text)
    except ValueError:
        value = float("nan")
    if not sep or not name or value != value:
        raise SystemExit(f"--set {item!r}; accepted: NAME=NUMBER, NAME a VerifierConfig field")
    return name.strip(), value


if __name__ == "__main__":
    sys.exit(main())

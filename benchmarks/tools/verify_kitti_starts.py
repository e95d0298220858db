"""The verifier with no initial guess on the four raw KITTI-00 scans, turned any way: does it find the pose?

    python benchmarks/tools/verify_kitti_starts.py [--trials 10] [--seed 0] [--reference registered] [--json FILE]
                                                   [--save VERDICTS.json] [--compare VERDICTS.json]

Every ordered pair of the scans 000000, 000001, 000005 and 000015 of ``../shared/data/kitti00``
(0.7 to 12 m apart), the query turned by ``--trials`` seeded random yaws in [0, 360) and shifted by up
to 2 m (:func:`lcpr_offline.kitti_scans.kitti_start_trials`). Each case is verified twice with the
default :class:`~lcpr_core.verification.VerifierConfig`: with no initial guess ("blind", what a loop
candidate gets) and from the true relative pose ("truth"). Printed: the share accepted with the right
pose (within 0.5 m / 3 deg), the reasons of rejection, the overlap (fitness) at the result and the
verification time, overall and per pair of scans, and the share whose result, accepted or not, has the
right pose ("pose found"). Where "truth" is right and "blind" is not, the starts failed; where the pose
is found but not accepted, the acceptance tests did. The known pose is poses.txt refined by a
dense registration of the raw scans (``--reference registered``, see
:func:`lcpr_offline.kitti_scans.registered_pose`: at the start of sequence 00 poses.txt is 0.2 to 1.3 m
off what the scans say); ``--reference poses`` takes poses.txt as it is.

Runs in well under a minute on two cores (120 cases); times are wall seconds of ``verify_prepared``.

``--save FILE`` writes every verdict (decision, reason, fitness, pose; named ``query-match/trial/blind`` and
``.../truth``, the trial counted within its pair of scans); ``--compare FILE`` checks this run's against such
a file (e.g. before and after a change to the verifier), prints what differs and exits with status 1 when a
decision or a reason differs or a pose moved more than 1 mm / 0.01 deg (:mod:`lcpr_offline.verdicts`).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lcpr_common.cli import tool_main

if TYPE_CHECKING:  # the package (and torch with it) is imported after the arguments are read
    from lcpr_core.verification import VerifierConfig

GUESSES = ("blind", "truth")  # the order kitti_start_trials verifies each case in


def summary(rows: list[dict[str, Any]], name: str) -> dict[str, Any]:
    """Share right, accepted, reasons, fitness (median over right / other results) and time of one guess kind."""
    right = np.array([bool(r[f"{name}_right"]) for r in rows])
    pose_ok = np.array([bool(r[f"{name}_pose_ok"]) for r in rows])
    accepted = np.array([bool(r[f"{name}_accepted"]) for r in rows])
    fitness = np.array([float(r[f"{name}_fitness"]) for r in rows])
    seconds = np.array([float(r[f"{name}_seconds"]) for r in rows])
    reasons = Counter(str(r[f"{name}_reason"]) for r in rows)
    wrong_pose = int((accepted & ~right).sum())
    return {
        "cases": len(rows), "right": float(right.mean()), "pose_ok": float(pose_ok.mean()),
        "accepted": float(accepted.mean()),
        "accepted_wrong_pose": wrong_pose, "reasons": dict(reasons.most_common()),
        "fitness_median_right": float(np.median(fitness[right])) if right.any() else None,
        "fitness_median_other": float(np.median(fitness[~right])) if (~right).any() else None,
        "ms_p50": float(np.median(seconds) * 1e3), "ms_p90": float(np.percentile(seconds, 90) * 1e3)}


@tool_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kitti", type=Path, default=None, help="the kitti00 folder (default: ../shared/data/kitti00)")
    p.add_argument("--trials", type=int, default=10, help="turned queries per ordered pair of scans")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reference", choices=("registered", "poses"), default="registered",
                   help="the known pose: poses.txt refined by registration (default), or poses.txt as it is")
    p.add_argument("--json", type=Path, default=None, help="also write the summary and every case here")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a numeric VerifierConfig field, e.g. fine_points=2048 (repeatable)")
    p.add_argument("--save", type=Path, default=None, help="write every verdict to this JSON file")
    p.add_argument("--compare", type=Path, default=None, help="compare the verdicts with a --save file")
    args = p.parse_args(argv)
    if args.compare is not None and not args.compare.is_file():
        raise SystemExit(f"--compare {args.compare}: no such file; accepted: a file written by --save")

    from lcpr_core.errors import VerificationError
    from lcpr_core.timing import cpu_model
    from lcpr_core.verification import VerifierConfig
    from lcpr_core.verification.config import with_settings
    from lcpr_offline import verdicts as verdict_file
    from lcpr_offline.kitti_scans import kitti_start_trials

    try:
        verifier = recording_verifier(with_settings(VerifierConfig(), args.set))
    except VerificationError as err:
        raise SystemExit(f"--set: {err}") from err
    rows = kitti_start_trials(verifier, trials=args.trials, seed=args.seed, folder=args.kitti,
                              reference=args.reference)
    print(f"CPU: {cpu_model()}, verifier threads {verifier.config.num_threads}; {len(rows)} cases "
          f"({args.trials} turns per ordered pair of scans, seed {args.seed}, reference {args.reference})")
    out: dict[str, Any] = {}
    for name in GUESSES:
        s = summary(rows, name)
        out[name] = s
        print(f"\n{name:5s}: right {s['right']:.2f}  pose found (accepted or not) {s['pose_ok']:.2f}  "
              f"accepted {s['accepted']:.2f} "
              f"(wrong pose {s['accepted_wrong_pose']})  time p50 {s['ms_p50']:.0f} ms, p90 {s['ms_p90']:.0f} ms")
        print(f"       reasons {s['reasons']}")
        print(f"       fitness median: right {s['fitness_median_right']}, other {s['fitness_median_other']}")
    print(f"\n{'query':>5s} {'match':>5s} {'dist m':>6s} | {'blind right':>11s} {'blind pose':>10s} "
          f"{'truth right':>11s} | "
          f"{'blind fitness':>13s} {'truth fitness':>13s} | blind reasons")
    per_pair: dict[str, Any] = {}
    for q, m in sorted({(int(r["query"]), int(r["match"])) for r in rows}):
        sub = [r for r in rows if r["query"] == q and r["match"] == m]
        b, t = summary(sub, "blind"), summary(sub, "truth")
        fb = np.median([float(r["blind_fitness"]) for r in sub])
        ft = np.median([float(r["truth_fitness"]) for r in sub])
        print(f"{q:5d} {m:5d} {float(sub[0]['distance_m']):6.1f} | {b['right']:11.2f} {b['pose_ok']:10.2f} "
              f"{t['right']:11.2f} | "
              f"{fb:13.2f} {ft:13.2f} | {b['reasons']}")
        per_pair[f"{q}-{m}"] = {"blind": b, "truth": t}
    out["per_pair"] = per_pair
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"summary": out, "cases": rows}, indent=2, default=float))
    return verdict_file.keep(_named(rows, verifier.verdicts), save_to=args.save, compare_with=args.compare,
                             same_run="run with the same --trials/--seed/--reference", indent="")


def recording_verifier(config: VerifierConfig) -> Any:
    """A GeometricVerifier that also keeps, in order, every verdict its callers get from ``verify_prepared``
    (``.verdicts``; the calls it makes itself are left out): kitti_start_trials returns no poses."""
    from lcpr_core.verification import GeometricVerifier, Verification

    class Recording(GeometricVerifier):
        def __init__(self, config: VerifierConfig) -> None:
            super().__init__(config)
            self.verdicts: list[Verification] = []
            self._depth = 0

        def verify_prepared(self, *args: Any, **kwargs: Any) -> Verification:
            self._depth += 1
            try:
                v = super().verify_prepared(*args, **kwargs)
            finally:
                self._depth -= 1
            if self._depth == 0:
                self.verdicts.append(v)
            return v

    return Recording(config)


def _named(rows: list[dict[str, Any]], verdicts: list[Any]) -> dict[str, Any]:
    """The verdict records by name, ``query-match/trial/guess``: each row's cases were verified in GUESSES' order."""
    from lcpr_offline.verdicts import record

    if len(verdicts) != len(GUESSES) * len(rows):
        raise AssertionError(f"{len(verdicts)} verdicts for {len(rows)} cases; expected {len(GUESSES)} a case")
    out: dict[str, Any] = {}
    trials: Counter[tuple[int, int]] = Counter()
    for k, row in enumerate(rows):
        pair = (int(row["query"]), int(row["match"]))
        for g, guess in enumerate(GUESSES):
            v = verdicts[len(GUESSES) * k + g]
            if (bool(v.accepted), str(v.reason)) != (bool(row[f"{guess}_accepted"]), str(row[f"{guess}_reason"])):
                raise AssertionError(f"case {k} ({guess}): the verdict kept is not the row's")
            out[f"{pair[0]}-{pair[1]}/{trials[pair]}/{guess}"] = record(v)
        trials[pair] += 1
    return out


if __name__ == "__main__":
    sys.exit(main())

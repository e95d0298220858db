"""The geometric verifier's verdicts kept in a file and compared: does a change to the verifier change what it decides?

A verdict record is what a :class:`~lcpr_core.verification.Verification` (or a verified
:class:`~lcpr_core.detector.Candidate`) decides: accepted or not, the reason, the fitness and the 4 x 4
relative pose (NaN where there is none). A run saves its records by a name per pair (:func:`save`); a later
run, e.g. after a change meant to make the verifier faster, compares its own with them (:func:`compare`): a
difference is a changed decision or reason, or a pose moved by more than :data:`POSE_TOLERANCE_M` /
:data:`POSE_TOLERANCE_DEG` (the fitness alone is not compared: it is printed beside a changed decision).
One home for the measuring tools (benchmarks/tools/verify_cost.py, verify_real.py, verify_kitti_starts.py)
and ``lcpr_eval --verdicts-save / --verdicts-compare``.
"""
from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lcpr_core.atomic import write_atomic
from lcpr_core.errors import InvalidValueError

if TYPE_CHECKING:
    from lcpr_core.detector import Candidate
    from lcpr_core.verification import Verification

#: A pose that moved more than this (m), or turned more than POSE_TOLERANCE_DEG, is a difference.
POSE_TOLERANCE_M = 1e-3
POSE_TOLERANCE_DEG = 1e-2
#: The keys of a record.
FIELDS = ("accepted", "reason", "fitness", "match_T_query")

Record = dict[str, Any]  # FIELDS: bool, str, float, 4 x 4 nested lists


def record(v: Verification) -> Record:
    """What a file keeps of a Verification: decision, reason, fitness and the 4 x 4 pose."""
    return {"accepted": bool(v.accepted), "reason": v.reason, "fitness": float(v.fitness),
            "match_T_query": np.asarray(v.match_T_query, np.float64).tolist()}


def candidate_record(c: Candidate) -> Record:
    """A detector candidate's verdict as :func:`record` keeps it (no pose, e.g. "no cloud": NaN)."""
    pose = np.full((4, 4), np.nan) if c.match_T_query is None else np.asarray(c.match_T_query, np.float64)
    return {"accepted": bool(c.verified), "reason": c.verification, "fitness": float(c.fitness),
            "match_T_query": pose.tolist()}


def differences(name: str, old: Record, new: Record) -> list[str]:
    """What differs between two records, one line each naming ``name`` (empty when the same verdict and pose)."""
    from lcpr_core.geometry import rotation_angle_deg

    out = []
    if (old["accepted"], old["reason"]) != (new["accepted"], new["reason"]):
        out.append(f"{name}: {old['reason']} -> {new['reason']} (fitness {old['fitness']:.4f} -> "
                   f"{new['fitness']:.4f})")
    a, b = np.asarray(old["match_T_query"], np.float64), np.asarray(new["match_T_query"], np.float64)
    if np.isfinite(a).all() and np.isfinite(b).all():
        delta = np.linalg.inv(a) @ b
        moved_m, moved_deg = float(np.linalg.norm(delta[:3, 3])), float(rotation_angle_deg(delta[:3, :3]))
        if moved_m > POSE_TOLERANCE_M or moved_deg > POSE_TOLERANCE_DEG:
            out.append(f"{name}: pose moved {moved_m:.4f} m, {moved_deg:.4f} deg")
    elif np.isfinite(a).all() != np.isfinite(b).all():
        out.append(f"{name}: pose finite {np.isfinite(a).all()} -> {np.isfinite(b).all()}")
    return out


def save(path: str | os.PathLike[str], records: Mapping[str, Record]) -> None:
    """Write the records by name as JSON (atomically; NaN poses as NaN, which :func:`load` reads back)."""
    text = json.dumps(dict(records), indent=1) + "\n"
    write_atomic(path, lambda tmp: tmp.write_text(text))


def load(path: str | os.PathLike[str]) -> dict[str, Record]:
    """The records a :func:`save` wrote, or InvalidValueError naming the file and what was expected."""
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        data = err
    if not isinstance(data, dict) or any(not isinstance(r, dict) or set(r) != set(FIELDS) for r in data.values()):
        raise InvalidValueError(f"{path}: not a verdicts file; expected a JSON object of records with the keys "
                               f"{', '.join(FIELDS)} (lcpr_offline.verdicts.save)")
    return data


def compare(path: str | os.PathLike[str], records: Mapping[str, Record], *, same_run: str) -> list[str]:
    """This run's records against a file's, name for name: a line per difference (empty when none).

    Names in one but not the other are one line, which asks to run with ``same_run`` (the options that
    choose the pairs); the names in both are compared with :func:`differences`.
    """
    reference = load(path)
    out = []
    if set(reference) != set(records):
        out.append(f"pairs differ from {path}: {len(set(reference) ^ set(records))} not in both ({same_run})")
    for key in sorted(set(reference) & set(records)):
        out += differences(f"{key} (vs {path})", reference[key], records[key])
    return out


def tally(records: Mapping[str, Record]) -> dict[str, int]:
    """How many records were accepted and how many were rejected for each reason (the accepted ones' reason)."""
    return dict(Counter(str(r["reason"]) for r in records.values()).most_common())


def keep(records: Mapping[str, Record], *, save_to: str | os.PathLike[str] | None,
         compare_with: str | os.PathLike[str] | None, same_run: str, indent: str = "  ") -> int:
    """A tool's --save and --compare: the records written to ``save_to`` and compared with ``compare_with``'s,
    the outcome printed (the first 20 differences); returns 1 when they differ, else 0 (an exit status)."""
    if save_to is not None:
        save(save_to, records)
        print(f"{indent}verdicts written to {save_to}")
    if compare_with is None:
        return 0
    found = compare(compare_with, records, same_run=same_run)
    print(f"{indent}verdicts compared: {len(found)} differences")
    for line in found[:20]:
        print(f"{indent}  {line}")
    return 1 if found else 0

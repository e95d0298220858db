"""lcpr_offline.verdicts: the verifier's verdicts saved, read back and compared (decision, reason, pose)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lcpr_core.detector import Candidate
from lcpr_core.errors import InvalidValueError
from lcpr_core.verification import Verification
from lcpr_offline import verdicts


def turned(deg: float, shift_m: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = 2.0 + shift_m
    return T


def test_a_saved_verdict_reads_back_the_same_a_missing_pose_as_nan(tmp_path: Path) -> None:
    accepted = verdicts.record(Verification(True, "accepted", turned(30.0), 0.8))
    candidate = Candidate(query_id=9, match_id=2, query_stamp=9.0, match_stamp=2.0, distance=0.3, rank=0,
                          match_position=None, degraded=False, verification="no cloud")
    missing = verdicts.candidate_record(candidate)
    assert missing["accepted"] is False and missing["reason"] == "no cloud" and np.isnan(missing["match_T_query"]).all()
    verdicts.save(tmp_path / "v.json", {"9-1": accepted, "9-2": missing})
    back = verdicts.load(tmp_path / "v.json")
    assert back["9-1"] == accepted and np.isnan(back["9-2"]["match_T_query"]).all()
    assert verdicts.compare(tmp_path / "v.json", {"9-1": accepted, "9-2": missing}, same_run="") == []
    assert verdicts.tally(back) == {"accepted": 1, "no cloud": 1}


def test_a_changed_reason_or_a_pose_moved_beyond_1_mm_or_0_01_deg_is_a_difference() -> None:
    old = verdicts.record(Verification(True, "accepted", turned(30.0), 0.8))
    assert verdicts.differences("p", old, verdicts.record(Verification(True, "accepted", turned(30.005, 5e-4),
                                                                       0.81))) == []
    rejected = verdicts.differences("p", old, verdicts.record(Verification(False, "ambiguous", turned(30.0), 0.8)))
    assert rejected == ["p: accepted -> ambiguous (fitness 0.8000 -> 0.8000)"]
    assert verdicts.differences("p", old, verdicts.record(Verification(True, "accepted", turned(30.0, 2e-3), 0.8))
                                ) == ["p: pose moved 0.0020 m, 0.0000 deg"]
    assert verdicts.differences("p", old, verdicts.record(Verification(True, "accepted", turned(30.02), 0.8))
                                ) == ["p: pose moved 0.0000 m, 0.0200 deg"]
    gone = dict(old, match_T_query=np.full((4, 4), np.nan).tolist())
    assert verdicts.differences("p", old, gone) == ["p: pose finite True -> False"]


def test_pairs_in_one_run_only_are_one_line_naming_the_options_to_repeat(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    v = verdicts.record(Verification(False, "low fitness", np.eye(4), 0.1))
    verdicts.save(tmp_path / "old.json", {"1-0": v, "2-0": v})
    found = verdicts.compare(tmp_path / "old.json", {"1-0": v, "3-0": v}, same_run="run with the same --seed")
    assert found == [f"pairs differ from {tmp_path / 'old.json'}: 2 not in both (run with the same --seed)"]
    assert verdicts.keep({"1-0": v, "2-0": v}, save_to=tmp_path / "new.json", compare_with=tmp_path / "old.json",
                         same_run="") == 0
    assert verdicts.load(tmp_path / "new.json") == {"1-0": v, "2-0": v}
    changed = dict(v, reason="sparse")
    assert verdicts.keep({"1-0": v, "2-0": changed}, save_to=None, compare_with=tmp_path / "old.json",
                         same_run="") == 1
    out = capsys.readouterr().out
    assert "verdicts compared: 1 differences" in out and "2-0 (vs " in out and "low fitness -> sparse" in out


def test_a_file_that_holds_no_verdicts_is_refused_naming_it(tmp_path: Path) -> None:
    (tmp_path / "report.json").write_text('{"methods": []}')
    with pytest.raises(InvalidValueError, match="report.json: not a verdicts file"):
        verdicts.load(tmp_path / "report.json")
    (tmp_path / "broken.json").write_text('{"1-0": ')
    with pytest.raises(InvalidValueError, match="broken.json"):
        verdicts.load(tmp_path / "broken.json")

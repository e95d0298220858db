"""lcpr_eval's verification on worker processes behind the network and the map: the verdicts of verifying each
keyframe as it is stored, every keyframe recorded in order, and each stage's share printed."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_evaluation import SMALL, write_loop_bag

import lcpr_offline.lcpr_evaluate as evaluation
from lcpr_core.errors import InvalidValueError
from lcpr_offline.lcpr_evaluate import EvalOptions, verification_workers


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("bags") / "loop"
    write_loop_bag(bag)
    return bag


def run(bag: Path, workers: int, monkeypatch: pytest.MonkeyPatch) -> tuple[Any, list[tuple[Any, ...]]]:
    """The report of ``workers`` and every keyframe's candidates as recorded (ids, verdict, pose bytes)."""
    from lcpr_ros.evaluate import evaluate_bag, options_from_args, parse_args

    recorded: list[tuple[Any, ...]] = []
    record = evaluation._record

    def keep(frame: Any, det_frame: Any, result: Any, run_record: Any) -> None:
        recorded.append((result.stamp, result.keyframe_id, tuple(
            (c.match_id, c.verified, c.verification, c.fitness, c.match_T_query.tobytes())
            for c in result.candidates)))
        record(frame, det_frame, result, run_record)
    monkeypatch.setattr(evaluation, "_record", keep)
    options = options_from_args(parse_args([str(bag), "--no-scan-context", "--workers", str(workers), *SMALL]))
    report = evaluate_bag(bag, options, progress=False)
    monkeypatch.undo()
    return report, recorded


@pytest.mark.slow  # two runs of the bag (test/lcpr_core/test_deferred_verification.py checks the detector quickly)
def test_verification_on_workers_behind_the_map_gives_the_verdicts_of_verifying_each_keyframe_in_process(
        loop_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    here, in_process = run(loop_bag, 0, monkeypatch)
    behind, on_workers = run(loop_bag, 2, monkeypatch)
    assert [r[0] for r in on_workers] == sorted(r[0] for r in on_workers) and len(on_workers) == 24  # in order
    assert on_workers == in_process and sum(len(r[2]) for r in in_process) >= 20  # every verdict, pose, fitness
    assert np.array_equal(behind.verified.fitness, here.verified.fitness)
    assert behind.settings["verify"]["processes"] == 2 and here.settings["verify"]["processes"] == 0
    stages = behind.stages
    assert stages.workers == 2 and stages.verify_busy > 0 and stages.verify_cpu > 0 and stages.describe > 0
    assert 0 < stages.store + stages.record + stages.network_wait + stages.verify_wait <= stages.run
    assert here.stages.workers == 0 and here.stages.verify_busy == 0
    assert behind.to_dict()["stages"]["workers"] == 2


def test_lcpr_eval_prints_keyframes_per_second_and_each_stage_s_share(
        loop_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_ros.evaluate import main

    assert main([str(loop_bag), "--out", str(tmp_path), "--no-scan-context", "--limit", "6", "--workers", "1",
                 *SMALL]) == 0
    text = capsys.readouterr().out
    assert "keyframes/s" in text and "network thread busy" in text and "1 verification workers busy" in text
    assert "search+store" in text and "waiting for the bag" in text


def test_the_workers_default_to_the_cores_this_process_may_run_on_and_a_bad_count_is_refused() -> None:
    from lcpr_core.verification import VerifierConfig
    from lcpr_ros.evaluate import options_from_args, parse_args

    assert verification_workers(EvalOptions()) == min(len(os.sched_getaffinity(0)), 64)
    assert verification_workers(EvalOptions(workers=3)) == 3
    assert verification_workers(EvalOptions(workers=3, verify=VerifierConfig(enabled=False))) == 0
    assert options_from_args(parse_args(["bag", "--workers", "5"])).workers == 5
    assert options_from_args(parse_args(["bag"])).workers is None
    for bad in (-1, 65, True, np.int64(2)):
        with pytest.raises(InvalidValueError, match=r"workers=.*accepted: 0\.\.64"):
            EvalOptions(workers=bad)  # type: ignore[arg-type]

"""Evaluation protocols on hand-made cases with known answers, the report, its plots and the lcpr_eval CLI."""
from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lcpr_core.evaluation import (
    EvaluationReport,
    MethodRun,
    database_query_protocol,
    evaluate_method,
    ground_truth,
    latency_stats,
    online_protocol,
    plot_latency,
    plot_pr_curves,
    plot_trajectory,
    pr_sweep,
    ranked_protocol,
    summary_table,
)
from lcpr_core.metrics import precision_recall, recall_at_n

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ a 1-D drive with one revisit
def line_drive() -> tuple[np.ndarray, np.ndarray]:
    """Rows 0..59: x = t = 0..59 (1 m, 1 s apart); rows 60..69: back at x = 0..9 at t = 100..109."""
    stamps = np.r_[np.arange(60.0), 100.0 + np.arange(10.0)]
    x = np.r_[np.arange(60.0), np.arange(10.0)]
    return stamps, np.c_[x, np.zeros(70), np.zeros(70)]


def line_candidates() -> tuple[np.ndarray, np.ndarray]:
    """Two ranked candidates per keyframe (rows into the keyframes), built so the answers are known.

    rows 30..59: one wrong candidate (30 m away) at distance 0.9;
    rows 60..64: correct top-1 at 0.1 .. 0.5;
    rows 65, 66: wrong top-1 (x = 50) at 0.15 and 0.6, correct second;
    rows 67..69: two wrong candidates, top-1 at 0.7, 0.8, 0.85.
    """
    ids = np.full((70, 2), -1)
    dist = np.full((70, 2), np.inf)
    for row in range(30, 60):
        ids[row, 0], dist[row, 0] = row - 30, 0.9
    for j, d in enumerate((0.1, 0.2, 0.3, 0.4, 0.5)):
        ids[60 + j] = (j, 40)
        dist[60 + j] = (d, 1.0)
    for j, d in ((5, 0.15), (6, 0.6)):
        ids[60 + j] = (50, j)
        dist[60 + j] = (d, 1.0)
    for j, d in ((7, 0.7), (8, 0.8), (9, 0.85)):
        ids[60 + j] = (50, 51)
        dist[60 + j] = (d, 1.0)
    return ids, dist


def test_a_revisit_is_a_true_loop_only_when_the_match_is_old_enough() -> None:
    gt = ground_truth(*line_drive())
    assert np.flatnonzero(gt.has_loop).tolist() == list(range(60, 70))
    # exactly exclude_recent_s older counts (the detector's rule), a hair less does not
    pos = np.array([[0.0, 0, 0], [100.0, 0, 0], [0.0, 0, 0]])
    assert ground_truth(np.array([0.0, 10.0, 30.0]), pos).has_loop.tolist() == [False, False, True]
    assert ground_truth(np.array([0.0, 10.0, 29.99]), pos).has_loop.tolist() == [False, False, False]


def test_the_database_is_the_first_pass_and_queries_are_the_revisits() -> None:
    gt = ground_truth(*line_drive())
    assert gt.split_time == 100.0 and gt.path_length == pytest.approx(59 + 59 + 9)
    assert gt.database.tolist() == list(range(60))  # stamped up to 100 - 30 s
    assert gt.queries.tolist() == list(range(60, 70))
    assert ground_truth(*line_drive(), split_time=105.0).queries.tolist() == list(range(65, 70))


def test_standing_still_is_a_loop_online_but_no_revisit_for_the_split() -> None:
    stamps = np.arange(60.0)
    x = np.r_[np.zeros(40), np.arange(1.0, 21.0) * 5]  # parked for 40 s, then drives away
    gt = ground_truth(stamps, np.c_[x, np.zeros(60)])
    assert gt.has_loop[30:40].all() and gt.split_time is None and len(gt.queries) == 0


def test_the_online_protocol_gives_the_hand_computed_recall_pr_and_f1() -> None:
    gt = ground_truth(*line_drive())
    res = online_protocol(gt, *line_candidates(), threshold=0.45)
    assert res.num_queries == 70 and res.num_positives == 10
    assert res.recall_at == pytest.approx({1: 0.5, 5: 0.7, 10: 0.7})  # K = 2 candidates: @5 = @10 = @2
    assert res.pr is not None
    # top-1 by distance: .1 T .15 F .2 T .3 T .4 T .5 T .6 F .7 F .8 F .85 F .9 F x30
    assert res.pr.thresholds[:6].tolist() == [0.1, 0.15, 0.2, 0.3, 0.4, 0.5]
    assert res.max_f1 == pytest.approx(2 * (5 / 6) * 0.5 / (5 / 6 + 0.5))  # 0.625 at 0.5
    assert res.pr.max_f1_threshold == 0.5
    assert res.recall_at_full_precision == pytest.approx(0.1)
    op = res.operating_point
    assert op is not None
    assert (op.true_positives, op.false_positives, op.false_negatives) == (4, 1, 6)
    assert op.precision == pytest.approx(0.8) and op.recall == pytest.approx(0.4)


def test_keyframes_without_a_position_are_not_queries_nor_correct_matches() -> None:
    stamps, pos = line_drive()
    pos[0] = np.nan  # row 60's correct match has no position now
    res = online_protocol(ground_truth(stamps, pos), *line_candidates())
    assert res.num_queries == 69 and 0 not in res.query_rows.tolist()
    assert res.recall_at[1] == pytest.approx(4 / 10)


def test_no_candidate_or_no_positive_query_gives_no_curve() -> None:
    gt = ground_truth(np.arange(3.0), np.c_[np.arange(3.0) * 50, np.zeros(3), np.zeros(3)])
    res = online_protocol(gt, np.full((3, 1), -1), np.full((3, 1), np.inf), threshold=1.0)
    assert res.num_positives == 0 and res.pr is None and res.recall_at == {} and res.max_f1 is None
    assert pr_sweep(np.array([np.inf]), np.array([False]), num_positives=1, num_queries=1) is None


def test_the_database_query_protocol_uses_the_metrics_on_l2_descriptors() -> None:
    gt = ground_truth(*line_drive())
    desc = np.zeros((70, 2))
    desc[:60, 0] = np.arange(60)  # database: one descriptor per metre
    desc[60:65, 0] = np.arange(5)  # revisits 0..4 look exactly like their places
    desc[65:, 0], desc[65:, 1] = 30 + 5 * np.arange(5), 0.5  # revisits 5..9 look like places 25+ m away
    res = database_query_protocol(gt, descriptors=desc)
    assert res is not None and res.num_database == 60 and res.num_queries == 10 and res.num_positives == 10
    assert res.recall_at == pytest.approx({1: 0.5, 5: 0.5, 10: 0.5})
    assert res.max_f1 == pytest.approx(2 / 3) and res.recall_at_full_precision == pytest.approx(0.5)
    assert res.top1_rows.tolist() == [0, 1, 2, 3, 4, 30, 35, 40, 45, 50]


def test_ranked_retrieval_agrees_with_the_metrics_module() -> None:
    rng = np.random.default_rng(4)
    db_pos, q_pos = rng.uniform(0, 60, (50, 2)), rng.uniform(0, 60, (30, 2))
    db_desc, q_desc = rng.normal(size=(50, 8)), rng.normal(size=(30, 8))
    d2 = ((q_desc[:, None] - db_desc[None]) ** 2).sum(2)
    order = np.argsort(d2, axis=1, kind="stable")[:, :10]
    has = (((q_pos[:, None] - db_pos[None]) ** 2).sum(2) <= 81).any(1)
    res = ranked_protocol(protocol="x", ranked_ids=order, ranked_distances=np.sqrt(np.take_along_axis(d2, order, 1)),
                          query_positions=q_pos, database_positions=db_pos, has_match=has, radius=9.0)
    want = recall_at_n(q_desc, db_desc, q_pos, db_pos, n_values=(1, 5, 10), threshold=9.0)
    pr = precision_recall(q_desc, db_desc, q_pos, db_pos, threshold=9.0)
    assert res.recall_at == pytest.approx(want.recalls) and res.num_positives == want.num_queries
    assert res.max_f1 == pytest.approx(pr.max_f1)
    assert res.pr is not None
    assert np.allclose(res.pr.precision, pr.precision) and np.allclose(res.pr.recall, pr.recall)


def test_latency_percentiles_per_stage_and_total_after_warmup() -> None:
    timings = [{"network": i / 1000, "search": 0.002} for i in range(1, 101)]
    stats = latency_stats(timings)
    assert stats["network"].p50_ms == pytest.approx(50.5) and stats["network"].count == 100
    assert stats["total"].p90_ms == pytest.approx(np.percentile(np.arange(1, 101) + 2.0, 90))
    assert latency_stats(timings, warmup=10)["search"].count == 90
    assert latency_stats(timings[:3], warmup=10)["search"].count == 3  # too few: all are kept
    with pytest.raises(ValueError, match="warmup=-1"):
        latency_stats(timings, warmup=-1)


def test_bad_inputs_are_refused_naming_the_value() -> None:
    with pytest.raises(ValueError, match="radius=0"):
        ground_truth(*line_drive(), radius=0)
    with pytest.raises(ValueError, match="not in time order"):
        ground_truth(np.array([1.0, 0.0]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="exactly one"):
        database_query_protocol(ground_truth(*line_drive()))
    with pytest.raises(Exception, match=r"\(3, 2\)"):
        online_protocol(ground_truth(*line_drive()), np.zeros((3, 2)), np.zeros((3, 2)))


def line_report() -> EvaluationReport:
    gt = ground_truth(*line_drive())
    ids, dist = line_candidates()
    timings = [{"network": 0.01 + 0.001 * i, "search": 0.0005} for i in range(70)]
    desc = np.eye(70)[:, :70]
    lcpr = MethodRun("LCPR", ids, dist, threshold=0.45, timings=timings, descriptors=desc)
    other = MethodRun("Other", ids[:, :1], dist[:, :1] / 2, threshold=0.2, timings=timings,
                      retrieve=lambda q, db, k: (np.full((len(q), k), 50), np.ones((len(q), k))), distance="x")
    methods = [evaluate_method(run, gt, warmup=5) for run in (lcpr, other)]
    counts = {"frames": 80, "keyframes": 70, "degraded_keyframes": 2, "dropped_clouds": 1}
    return EvaluationReport(source="line", settings={"warmup": 5}, counts=counts, ground_truth=gt, methods=methods)


def test_the_report_is_written_as_plain_json_atomically(tmp_path: Path) -> None:
    report = line_report()
    report.write_json(tmp_path / "report.json")
    data = json.loads((tmp_path / "report.json").read_text())
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]  # no temporary file left behind
    lcpr = data["methods"][0]
    assert lcpr["online"]["recall_at"] == pytest.approx({"1": 0.5, "5": 0.7, "10": 0.7})
    assert lcpr["online"]["max_f1"] == pytest.approx(0.625)
    assert len(lcpr["online"]["accepted_loops"]) == 5
    assert lcpr["database_query"]["num_queries"] == 10 and lcpr["latency_ms"]["total"]["count"] == 65
    assert data["methods"][1]["database_query"]["recall_at"]["1"] == 0.0  # always x = 50: 41+ m off
    assert data["ground_truth"]["queries_with_true_loop"] == 10 and data["counts"]["frames"] == 80


def test_the_report_reader_reads_back_the_online_figures_the_report_writer_wrote(tmp_path: Path) -> None:
    from lcpr_core.evaluation.eval_report import online, online_methods

    report = line_report()
    report.write_json(tmp_path / "report.json")
    methods = online_methods(tmp_path / "report.json")
    assert list(methods) == ["LCPR", "Other"]
    lcpr = report.methods[0].online
    assert lcpr.pr is not None
    assert methods["LCPR"]["recall@1"] == pytest.approx(0.5) and methods["LCPR"]["max_f1"] == pytest.approx(0.625)
    assert methods["LCPR"]["max_f1_threshold"] == pytest.approx(lcpr.pr.max_f1_threshold)
    assert online(tmp_path / "report.json") == (pytest.approx(0.5), pytest.approx(0.625))


def test_the_summary_table_lists_both_protocols_for_each_method() -> None:
    text = summary_table(line_report())
    assert "Recall@1/@5/@10" in text and "LCPR" in text and "Other" in text
    assert "0.50 / 0.70 / 0.70" in text and "4/1 @ 0.45" in text and "60 database keyframes" in text


def test_the_three_figures_are_png_files(tmp_path: Path) -> None:
    report = line_report()
    plot_pr_curves(report.methods, tmp_path / "pr.png")
    plot_latency(report.methods, tmp_path / "latency.png", warmup=5)
    plot_trajectory(report.ground_truth, report.methods, tmp_path / "trajectory.png")
    for name in ("pr.png", "latency.png", "trajectory.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------ the CLI on a bag made here
def jpeg(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=80)
    return buf.getvalue()


def write_loop_bag(path: Path, *, frames: int = 24) -> None:
    """1.5 laps of a 20 m circle, 16 frames a lap, 2.5 s apart: frames 16.. revisit frames 0.. after 40 s.

    Cloud: world landmarks (poles) seen from the pose; images: six 48 x 128 JPEGs coloured by place.
    """
    from msg_tools import NUSCENES_TOPICS, BagWriter, CameraImage, SensorFrame, xyz_cloud

    rng = np.random.default_rng(0)
    poles = rng.uniform(-70, 70, size=(120, 2))
    poles = poles[np.hypot(*poles.T) > 25]  # keep the road clear
    tops = rng.uniform(1.0, 9.0, size=len(poles))
    with BagWriter(path) as writer:
        for i in range(frames):
            t = 1_700_000_000.0 + 2.5 * i
            angle = 2 * np.pi * i / 16
            yaw = angle + np.pi / 2
            pose = np.eye(4)
            pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            pose[:2, 3] = 20 * np.cos(angle), 20 * np.sin(angle)
            noise = np.random.default_rng(i)
            k = noise.integers(0, len(poles), 3000)
            world = np.c_[poles[k] + noise.normal(scale=0.3, size=(3000, 2)), noise.uniform(0, 1, 3000) * tops[k]]
            local = (world[:, :2] - pose[:2, 3]) @ pose[:2, :2]  # world -> vehicle frame
            cloud = xyz_cloud(np.c_[local, world[:, 2] - 1.8], intensity=noise.random(3000).astype(np.float32))
            place = np.random.default_rng(100 + i % 16)
            cams: list[CameraImage | None] = []
            for c in range(6):
                rgb = np.clip(place.integers(0, 256, (1, 1, 3)) + noise.normal(0, 8, (48, 128, 3)), 0, 255)
                cams.append(CameraImage(t + 0.001 * c, f"cam{c}", jpeg=jpeg(rgb.astype(np.uint8))))
            writer.write_frame(SensorFrame(t, cams, cloud, "lidar", pose), topics=NUSCENES_TOPICS)


SMALL = ["--seeded", "--image-size", "32", "96", "--lidar", "velodyne_vlp16", "--threads", "1", "--quiet",
         "--warmup", "1"]


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("bags") / "loop"
    write_loop_bag(bag)
    return bag


@pytest.mark.slow
def test_lcpr_eval_runs_a_bag_and_writes_the_report_and_figures(loop_bag: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_ros.evaluate import main

    out = tmp_path / "eval"
    assert main([str(loop_bag), "--out", str(out), *SMALL]) == 0
    text = capsys.readouterr().out
    assert "Recall@1/@5/@10" in text and "Scan Context" in text and "random weights" in text
    assert sorted(p.name for p in out.iterdir()) == ["latency.png", "pr_curve.png", "report.json", "trajectory.png"]
    report = json.loads((out / "report.json").read_text())
    assert report["counts"]["frames"] == 24 and report["counts"]["keyframes"] == 24
    # frames 16..23 revisit frames 0..7; frame 15 (37.5 s) ends lap one 7.8 m before frame 0
    assert report["ground_truth"]["queries_with_true_loop"] == 9
    assert report["ground_truth"]["split_offset_s"] == 37.5 and report["ground_truth"]["database_size"] == 4
    lcpr, sc = report["methods"]
    assert lcpr["name"] == "LCPR" and set(lcpr["latency_ms"]) >= {"preprocess", "network", "search", "add", "total"}
    assert all(0.0 <= r <= 1.0 for r in lcpr["online"]["recall_at"].values())
    # the same places seen again from the same poses: Scan Context accepts every exact revisit, nothing else
    assert sc["online"]["recall_at"]["5"] == 1.0
    assert sorted(loop["query"] for loop in sc["online"]["accepted_loops"] if loop["correct"]) == list(range(16, 24))
    assert sc["online"]["operating_point"]["false_positives"] == 0


def test_lcpr_eval_lidar_only_reads_no_camera_and_describes_every_keyframe_with_empty_slots(
        loop_bag: Path, tmp_path: Path) -> None:
    from lcpr_ros.evaluate import main, options_from_args, parse_args

    assert main([str(loop_bag), "--out", str(tmp_path), "--limit", "6", "--no-scan-context", "--lidar-only",
                 *SMALL]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["counts"]["keyframes"] == 6 and report["counts"]["degraded_keyframes"] == 6
    assert report["settings"]["topics"]["cameras"] == [] and report["settings"]["model"]["num_cameras"] == 6
    scans = options_from_args(parse_args([str(loop_bag), "--topics", "scans"]))
    assert scans.lidar_only and scans.topics.lidar == "/points" and scans.topics.odom == "/odom"


def test_lcpr_eval_on_a_short_prefix_without_loops_still_reports(loop_bag: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_ros.evaluate import main

    assert main([str(loop_bag), "--out", str(tmp_path), "--limit", "4", "--no-scan-context", *SMALL]) == 0
    assert "protocol not applicable" in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["counts"]["keyframes"] == 4 and len(report["methods"]) == 1
    assert report["methods"][0]["database_query"] is None and report["methods"][0]["online"]["max_f1"] is None


def test_lcpr_eval_refuses_bad_options_and_missing_bags_with_a_message(tmp_path: Path, loop_bag: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_ros.evaluate import main

    assert main([str(tmp_path / "nothing"), "--out", str(tmp_path)]) == 2
    assert "not a rosbag2 folder" in capsys.readouterr().err
    assert main([str(loop_bag), "--out", str(tmp_path), "--seeded", "--image-size", "30", "90", "--quiet"]) == 2
    assert "image_size=(30, 90)" in capsys.readouterr().err
    assert main([str(loop_bag), "--radius", "-1", "--quiet"]) == 2
    assert "radius=-1" in capsys.readouterr().err


def test_the_evaluation_cli_does_not_import_rclpy() -> None:
    code = "import sys, lcpr_ros.evaluate; sys.exit('rclpy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


@pytest.mark.slow
def test_lcpr_eval_on_a_synthetic_city_drive_finds_its_revisits(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    synth = pytest.importorskip("citysim")
    drive = synth.SyntheticDrive(synth.SynthConfig(frames=48, seed=3, keyframe_spacing=20.0, image_size=(200, 112)))
    synth.write_bag(drive, tmp_path / "city")
    assert main_ok([str(tmp_path / "city"), "--out", str(tmp_path / "eval"), *SMALL])
    assert "Scan Context" in capsys.readouterr().out
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert report["ground_truth"]["queries_with_true_loop"] > 5 and report["ground_truth"]["query_count"] > 5
    sc = report["methods"][1]
    assert sc["online"]["operating_point"]["source"] == "max F1"
    assert sc["online"]["recall_at"]["10"] >= 0.5 and sc["database_query"]["recall_at"]["10"] >= 0.5


def main_ok(argv: list[str]) -> bool:
    from lcpr_ros.evaluate import main

    return main(argv) == 0


# ------------------------------------------------------------------ LCPR + verification
def test_verified_loops_are_scored_by_the_loop_report_rule_and_reported_beside_retrieval() -> None:
    from lcpr_core.evaluation import evaluate_verified
    from lcpr_core.loop_report import PublishedLoop

    report = line_report()
    gt = report.ground_truth
    world_T_lidar = np.tile(np.eye(4), (70, 1, 1))
    world_T_lidar[:, :3, 3] = gt.positions
    est = np.eye(4)
    est[:3, 3] = (0.0, 0.2, 0.0)  # the truth between rows 60 + j and j is identity: 0.2 m off, 0 deg
    loops = [PublishedLoop(60, 0, est, np.eye(6) * 0.01), PublishedLoop(61, 1, est, None),
             PublishedLoop(62, 40), PublishedLoop(35, 0, est, None)]  # 62 -> 40 and 35 -> 0: wrong
    verified = evaluate_verified(gt, loops, [0.9, 0.6, 0.8, 0.5], world_T_lidar=world_T_lidar)
    s = verified.score
    assert (s.loops, s.correct, s.closed, s.true_revisits) == (4, 2, 2, 10)
    assert s.precision == pytest.approx(0.5) and s.recall == pytest.approx(0.2)
    assert s.trans_err_median == pytest.approx(0.2) and s.yaw_err_p95 == pytest.approx(0.0, abs=1e-9)
    # by fitness: .9 T, .8 F, .6 T, .5 F -> R at P=1 is 0.1; max F1 at fitness 0.6: P 2/3, R 0.2
    assert verified.recall_at_full_precision == pytest.approx(0.1)
    assert verified.max_f1 == pytest.approx(2 * (2 / 3) * 0.2 / (2 / 3 + 0.2)) and verified.max_f1_min_fitness == 0.6
    with pytest.raises(ValueError, match="share a query"):
        evaluate_verified(gt, loops[:2] + [PublishedLoop(60, 2)], [0.9, 0.6, 0.5])

    report.verified = verified
    data = json.loads(json.dumps(report.to_dict(), allow_nan=False))["verified"]
    assert data["precision"] == 0.5 and data["loops"] == 4 and data["pr_curve"]["min_fitness"][0] == 0.9
    assert [(a["query"], a["correct"]) for a in data["accepted_loops"]] == [(60, True), (61, True), (62, False),
                                                                            (35, False)]
    assert data["accepted_loops"][0]["trans_err_m"] == pytest.approx(0.2) and data["pose_graph"] is None
    text = summary_table(report)
    assert "LCPR (retrieval)" in text and "LCPR + verification" in text
    assert "0.80 / 0.40" in text and "0.50 / 0.20" in text and "0.200 / 0.00" in text  # retrieval | verified


def test_the_verified_table_and_the_report_judge_verified_loops_by_their_pose_in_three_groups() -> None:
    from lcpr_core.evaluation import evaluate_verified
    from lcpr_core.loop_report import PublishedLoop

    report = line_report()
    gt = report.ground_truth
    world_T_lidar = np.tile(np.eye(4), (70, 1, 1))
    world_T_lidar[:, :3, 3] = gt.positions
    off = np.eye(4)
    off[:3, 3] = (1.0, 0.0, 0.0)
    loops = [PublishedLoop(60, 0, np.eye(4)),  # right pose within 9 m (0 m apart)
             PublishedLoop(61, 21, np.linalg.inv(world_T_lidar[21]) @ world_T_lidar[61]),  # right pose 20 m apart
             PublishedLoop(62, 32, off)]  # 30 m apart, 30 m off: wrong pose
    verified = evaluate_verified(gt, loops, [0.9, 0.8, 0.7], world_T_lidar=world_T_lidar)
    s = verified.score
    assert (s.right_within_radius, s.right_beyond_radius, s.wrong_pose, s.unjudged) == (1, 1, 1, 0)
    assert s.precision_by_pose == pytest.approx(2 / 3) and s.precision == pytest.approx(1 / 3)  # by pose, by radius
    # the fitness sweep counts a loop right by its pose too: .9 right, .8 right (20 m apart), .7 wrong pose
    assert verified.recall_at_full_precision == pytest.approx(0.2)
    report.verified = verified
    data = json.loads(json.dumps(report.to_dict(), allow_nan=False))["verified"]
    assert (data["right_within_radius"], data["right_beyond_radius"], data["wrong_pose"]) == (1, 1, 1)
    assert data["precision_by_pose"] == pytest.approx(2 / 3) and data["wrong_with_true_pose"] == 1
    assert [(a["correct"], a["right_pose"]) for a in data["accepted_loops"]] == [(True, True), (False, True),
                                                                                 (False, False)]
    lines = {line[:34].strip(): line[34:].split() for line in summary_table(report).splitlines()}
    assert lines["online     loops (right/wrong)"][-2:] == ["3", "(2/1)"]
    assert lines["right pose <= / > 9 m"][-3:] == ["1", "/", "1"]
    assert lines["online     precision / recall"][-3:] == ["0.67", "/", "0.10"]
    assert " ".join(lines["right means"]) == "within 9 m pose 0.3 m / 2 deg"


def test_the_lidar_extrinsic_comes_from_tf_static_or_is_identity(tmp_path: Path) -> None:
    from lcpr_ros.evaluate import base_T_lidar_of
    from msg_tools import NUSCENES_TOPICS, BagWriter, SensorFrame, xyz_cloud

    mount = np.eye(4)
    mount[:3, :3] = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    mount[:3, 3] = (0.94, 0.0, 1.84)
    with BagWriter(tmp_path / "tf") as writer:
        writer.write_static_transforms([], "LIDAR_TOP", mount)
        writer.write_frame(SensorFrame(1.0, [], xyz_cloud(np.zeros((3, 3))), "LIDAR_TOP", np.eye(4)),
                           topics=NUSCENES_TOPICS)
    found, source = base_T_lidar_of(tmp_path / "tf", "LIDAR_TOP")
    np.testing.assert_allclose(found, mount, atol=1e-9)
    assert source == "/tf_static base_link -> LIDAR_TOP"
    found, source = base_T_lidar_of(tmp_path / "tf", "velodyne")
    assert np.array_equal(found, np.eye(4)) and "no /tf_static transform links 'base_link' to 'velodyne'" in source


def test_lcpr_eval_reports_the_verified_loops_beside_retrieval(loop_bag: Path) -> None:
    from lcpr_ros.evaluate import evaluate_bag, options_from_args, parse_args

    options = options_from_args(parse_args([str(loop_bag), "--no-scan-context", *SMALL]))
    report = evaluate_bag(loop_bag, options, progress=False)
    verified = report.verified
    assert verified is not None and verified.name == "LCPR + verification"
    s = verified.score
    keyframes = report.counts["keyframes"]
    assert keyframes == 24 and 0 <= s.correct <= s.loops <= keyframes
    assert s.precision is None or 0.0 <= s.precision <= 1.0
    assert s.recall is not None
    assert s.true_revisits == 9 and 0.0 <= s.recall <= 1.0
    assert all(0.0 <= f <= 1.0 for f in verified.fitness)
    assert "identity" in verified.base_T_lidar_source  # the bag has no /tf_static: clouds are in the base frame
    assert verified.pose_graph is not None or verified.pose_graph_note
    data = report.to_dict()
    assert data["verified"]["loops"] == s.loops and data["settings"]["verify"]["enabled"] is True
    assert "LCPR + verification" in summary_table(report)
    # --no-verify: retrieval only, as before
    options = options_from_args(parse_args([str(loop_bag), "--no-scan-context", "--no-verify", "--limit", "4",
                                            *SMALL]))
    plain = evaluate_bag(loop_bag, options, progress=False)
    assert plain.verified is None and plain.to_dict()["verified"] is None
    assert "LCPR + verification" not in summary_table(plain)


def test_lcpr_eval_with_the_node_s_params_file_evaluates_what_the_node_would_run(tmp_path) -> None:
    """One configuration source: the parameter file sets model, keyframing, matching, verification and topics."""
    import yaml

    from lcpr_ros.evaluate import options_from_args, parse_args
    from lcpr_ros.params import settings_from_file

    repo = Path(__file__).resolve().parents[2]
    data = yaml.safe_load((repo / "config" / "lcpr.yaml").read_text())
    params = data["/**"]["ros__parameters"]
    params["match"]["exclude_recent_s"] = 12.5
    params["keyframe"]["min_interval"] = 2.0
    params["verify"]["min_fitness"] = 0.6
    params["model"]["image_size"] = [64, 192]
    params["lidar_topic"] = "/my/points"
    params["sync"]["slop"] = 0.02
    path = tmp_path / "vehicle.yaml"
    path.write_text(yaml.safe_dump(data))
    node = settings_from_file(path)
    options = options_from_args(parse_args([str(tmp_path / "bag"), "--params-file", str(path), "--weights", "w.pth"]))
    assert options.exclude_recent_s == 12.5 == node.detector.match.exclude_recent_s
    assert options.keyframe == node.detector.keyframe and options.keyframe.min_interval == 2.0
    assert options.verify == node.detector.verify and options.verify.min_fitness == 0.6
    assert options.model.image_size == (64, 192) and options.model.weights == "w.pth"
    assert options.topics.lidar == "/my/points" and options.topics.cameras == node.node.camera_topics
    assert options.slop == 0.02 and options.max_distance == node.detector.match.max_distance


def test_lcpr_eval_runs_the_bundled_weights_unless_random_ones_are_asked_for_by_name(tmp_path: Path) -> None:
    from lcpr_ros.evaluate import options_from_args, parse_args

    bag = str(tmp_path / "bag")
    assert options_from_args(parse_args([bag])).model.weights == "bundled"
    assert options_from_args(parse_args([bag, "--seeded"])).model.weights == "seeded"
    assert options_from_args(parse_args([bag, "--weights", "w.pth"])).model.weights == "w.pth"
    assert options_from_args(parse_args([bag])).max_distance == -1.0  # automatic, as the node


def test_lcpr_eval_refuses_a_params_file_with_flags_that_set_the_same_things(tmp_path) -> None:
    from lcpr_ros.evaluate import main

    repo = Path(__file__).resolve().parents[2]
    assert main([str(tmp_path / "bag"), "--params-file", str(repo / "config" / "lcpr.yaml"),
                 "--exclude-recent", "10"]) == 2
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    match:\n      top_kk: 3\n")
    assert main([str(tmp_path / "bag"), "--params-file", str(bad)]) == 2


def test_the_evaluation_describes_sixteen_frames_per_network_call_on_a_gpu_and_one_on_the_cpu_unless_told():
    from lcpr_core.errors import InvalidValueError
    from lcpr_core.lcpr.describer import ModelConfig
    from lcpr_offline.lcpr_evaluate import CUDA_BATCH, EvalOptions, frames_per_call

    assert frames_per_call(EvalOptions()) == 1
    assert frames_per_call(EvalOptions(model=ModelConfig(device="cuda:0"))) == CUDA_BATCH == 16
    assert frames_per_call(EvalOptions(batch=4, model=ModelConfig(device="cuda:0"))) == 4
    with pytest.raises(InvalidValueError, match=r"batch=-2; it must be >= 1 frame, or 0 \(auto\)"):
        EvalOptions(batch=-2)


@pytest.mark.slow
def test_lcpr_eval_saves_every_candidate_s_verdict_and_compares_a_later_run_with_them(
        loop_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lcpr_offline.verdicts import load, save
    from lcpr_ros.evaluate import main

    args = [str(loop_bag), "--out", str(tmp_path / "eval"), "--no-scan-context", *SMALL]
    assert main([*args, "--verdicts-save", str(tmp_path / "v.json")]) == 0
    kept = load(tmp_path / "v.json")
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert kept and len(kept) >= report["verified"]["loops"]  # every candidate, not only each keyframe's loop
    assert main([*args, "--verdicts-compare", str(tmp_path / "v.json")]) == 0
    assert "verdicts compared: 0 differences" in capsys.readouterr().out
    name = sorted(kept)[0]
    save(tmp_path / "changed.json", {**kept, name: dict(kept[name], accepted=not kept[name]["accepted"])})
    assert main([*args, "--verdicts-compare", str(tmp_path / "changed.json")]) == 1
    assert f"verdicts compared: 1 differences\n  {name} (vs " in capsys.readouterr().out
    assert main([*args, "--no-verify", "--verdicts-save", str(tmp_path / "w.json")]) == 2
    assert "need verification, which is off here" in capsys.readouterr().err

"""Several sessions in one graph: a second run placed in the first one's map by loops that agree, and not fooled."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

from lcpr_core.backend import BackendConfig, PoseGraphBackend  # noqa: E402
from lcpr_core.backend.placing import ANCHORS, INTER_WAITING, REANCHORS  # noqa: E402
from lcpr_core.errors import BackendError  # noqa: E402
from lcpr_core.geometry import rotation_angle_deg  # noqa: E402
from lcpr_core.posegraph import DriftModel, drift_odometry  # noqa: E402
from trajectory_fixtures import pose, square_laps  # noqa: E402

T0, T1 = 1_700_000_000.0, 1_700_090_000.0  # the first session's stamps, the second's (a day later)
DT = 0.1
LOOP_COV = np.diag([0.05**2] * 3 + [math.radians(0.5) ** 2] * 3)
MOVED = pose(130.0, -45.0, 3.0, yaw=117.0, roll=2.0)  # the second run's odometry frame in the world


class Two:
    """Two drives round one square: ``a`` from one corner (nearly exact odometry: its frame is the world), ``b``
    from another, its odometry drifting and expressed in a frame moved by MOVED^-1."""

    def __init__(self, *, seed: int = 1) -> None:
        truth, per_lap = square_laps(side=40.0, step=0.5, laps=1)
        self.truth_a = truth
        self.truth_b = np.roll(truth, -per_lap // 4, axis=0)  # starts a side further on
        self.odom_a, _ = drift_odometry(truth, model=DriftModel(seed=seed, translation_frac=1e-4, z_frac=1e-4,
                                                                 yaw_deg_per_m=1e-3, roll_pitch_deg_per_m=1e-3))
        drifted, _ = drift_odometry(self.truth_b, model=DriftModel(seed=seed + 1, yaw_deg_per_m=0.2))
        self.odom_b = np.linalg.inv(MOVED) @ drifted
        self.stamps_a = T0 + DT * np.arange(len(truth))
        self.stamps_b = T1 + DT * np.arange(len(truth))

    def graph(self, config: BackendConfig | None = None) -> PoseGraphBackend:
        """A graph of session a alone (live: a later session's loops may bend it)."""
        g = PoseGraphBackend(config)
        for t, p in zip(self.stamps_a, self.odom_a, strict=True):
            g.add_odometry(float(t), p, session="a")
        return g

    def prior(self, folder: Path) -> PoseGraphBackend:
        """Session a saved and loaded as a prior map, held at its estimates."""
        self.graph().save(folder / "a.npz")
        return PoseGraphBackend.load(folder / "a.npz", hold=True)

    def feed_b(self, g: PoseGraphBackend, upto: int, start: int = 0) -> None:
        for i in range(start, upto):
            g.add_odometry(float(self.stamps_b[i]), self.odom_b[i], session="b")

    def true_map_T_odom(self, i: int) -> np.ndarray:
        """b's odometry frame in the world at its pose ``i`` (its drift so far included)."""
        return self.truth_b[i] @ np.linalg.inv(self.odom_b[i])

    def true_loop(self, i: int) -> tuple[float, float, np.ndarray]:
        """(query stamp in b, match stamp in a, match_T_query) of b's pose ``i`` and the nearest pose of a."""
        j = int(np.argmin(np.linalg.norm(self.truth_a[:, :3, 3] - self.truth_b[i, :3, 3], axis=1)))
        return float(self.stamps_b[i]), float(self.stamps_a[j]), np.linalg.inv(self.truth_a[j]) @ self.truth_b[i]


def pose_error(a: np.ndarray | None, b: np.ndarray) -> tuple[float, float]:
    assert a is not None
    d = np.linalg.inv(a) @ b
    return float(np.linalg.norm(d[:3, 3])), float(rotation_angle_deg(d[:3, :3]))


def frame_error(two: Two, g: PoseGraphBackend, i: int) -> tuple[float, float]:
    """How far map_T_odom("b") puts b's pose ``i`` from the truth (m, deg): a frame's error where the robot is,
    not at its origin (a 130 m lever would turn 0.1 deg into 0.2 m)."""
    est = g.map_T_odom("b")
    assert est is not None
    return pose_error(est @ two.odom_b[i], two.truth_b[i])


def test_a_session_in_a_moved_frame_is_placed_in_a_prior_map_by_agreeing_loops_and_lands_on_the_truth(
        tmp_path: Path) -> None:
    two = Two()
    g = two.prior(tmp_path)
    assert g.sessions == ["a"] and g.anchored("a")
    two.feed_b(g, 10)
    assert not g.anchored("b") and g.map_T_odom("b") is None
    _, own = g.trajectory("b")
    np.testing.assert_allclose(own, two.odom_b[:10], atol=1e-6)  # its own frame until placed
    placed_at = None
    for i in range(10, 200):
        g.add_odometry(float(two.stamps_b[i]), two.odom_b[i], session="b")
        if i % 10 == 0:
            q, m, rel = two.true_loop(i)
            g.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="a")
            if placed_at is None and g.anchored("b"):
                placed_at = i
    assert placed_at is not None and (placed_at - 10) * 0.5 <= 20.0  # within 20 m of the first loop's place
    stats = g.stats()
    assert stats.inter_session[ANCHORS] == 1 and stats.inter_session.get(REANCHORS, 0) == 0
    assert stats.last_anchor_s is not None
    err_m, err_deg = frame_error(two, g, 199)
    assert err_m < 0.3 and err_deg < 1.0
    stamps, traj = g.trajectory("b")
    ate = float(np.sqrt(np.mean(np.sum((traj[:, :3, 3] - two.truth_b[:200, :3, 3]) ** 2, axis=1))))
    assert ate < 0.5
    assert g.session_loops()[0][0] == "b" and g.session_loops()[0][2] == "a"


def test_twenty_random_wrong_inter_session_loops_never_place_a_session_and_are_all_counted() -> None:
    two = Two(seed=3)
    g = two.graph()
    two.feed_b(g, len(two.stamps_b))
    rng = np.random.default_rng(0)
    for _ in range(20):
        i, j = int(rng.integers(0, len(two.stamps_b))), int(rng.integers(0, len(two.stamps_a)))
        rel = pose(*rng.uniform(-3, 3, 2), yaw=float(rng.uniform(-30, 30)))
        g.add_loop(float(two.stamps_b[i]), float(two.stamps_a[j]), rel, LOOP_COV, query_session="b",
                   match_session="a")
        assert not g.anchored("b")
    assert g.stats().inter_session[INTER_WAITING] == 20 and g.stats().loops_accepted == 0


def test_five_look_alike_loops_that_agree_are_overturned_once_more_true_loops_arrive(tmp_path: Path) -> None:
    two = Two(seed=5)
    g = two.prior(tmp_path)
    look_alike = pose(8.0, 0.0, yaw=0.0)  # a street that looks like another 8 m along
    two.feed_b(g, 60)
    for i in range(10, 60, 10):  # five wrong loops, consistent with one another
        q, m, rel = two.true_loop(i)
        g.add_loop(q, m, look_alike @ rel, LOOP_COV, query_session="b", match_session="a")
    assert g.anchored("b")  # wrongly: nothing could tell
    assert frame_error(two, g, 59)[0] > 5.0
    wrong_until = None
    for i in range(60, len(two.stamps_b)):
        g.add_odometry(float(two.stamps_b[i]), two.odom_b[i], session="b")
        if i % 10 == 0:
            q, m, rel = two.true_loop(i)
            g.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="a")
            if wrong_until is None and frame_error(two, g, i)[0] < 0.5:
                wrong_until = i
    assert wrong_until is not None and (wrong_until - 60) * 0.5 <= 40.0  # corrected within 40 m of true loops
    stats = g.stats()
    assert stats.inter_session[REANCHORS] == 1 and stats.inter_session["withdrawn"] == 5
    err_m, err_deg = frame_error(two, g, len(two.stamps_b) - 1)
    assert err_m < 0.5 and err_deg < 1.0


def test_a_loop_naming_a_session_the_graph_does_not_know_is_refused_counted_and_changes_nothing() -> None:
    two = Two()
    g = two.graph()
    two.feed_b(g, 50)
    before = g.trajectory("b")[1]
    q, m, rel = two.true_loop(20)
    with pytest.raises(BackendError, match=r"match_session='c' is not a session of this graph \(it holds 'a', 'b'\)"):
        g.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="c")
    with pytest.raises(BackendError, match=r"session='' ; expected a non-empty name|session=''; expected"):
        g.add_odometry(T1 + 99.0, np.eye(4), session="")
    assert g.stats().refused == {"loop session unknown": 1, "bad session": 1}
    np.testing.assert_array_equal(g.trajectory("b")[1], before)
    with pytest.raises(BackendError, match=r"session='c' is not a session"):
        g.anchored("c")


def test_a_saved_graph_of_sessions_loads_as_the_prior_of_a_new_session(tmp_path: Path) -> None:
    two = Two()
    g = two.graph()
    g.save(tmp_path / "a.npz")
    prior = PoseGraphBackend.load(tmp_path / "a.npz", hold=True)
    assert prior.sessions == ["a"] and prior.anchored("a")
    for i in range(0, 120):
        prior.add_odometry(float(two.stamps_b[i]), two.odom_b[i], session="b")
        if i % 10 == 0 and i:
            q, m, rel = two.true_loop(i)
            prior.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="a")
    assert prior.anchored("b")
    prior.save(tmp_path / "ab.npz")
    again = PoseGraphBackend.load(tmp_path / "ab.npz")
    assert again.sessions == ["a", "b"] and again.anchored("b")
    np.testing.assert_allclose(again.trajectory("b")[1], prior.trajectory("b")[1], atol=2e-3)
    assert again.stats().inter_session[ANCHORS] == 1
    assert again.session_loops() == prior.session_loops()
    with pytest.raises(BackendError, match=r"session='a' is a prior map held at its estimates"):
        prior.add_odometry(T0 + 1e4, np.eye(4), session="a")


def test_a_prior_graph_is_checked_against_the_descriptor_map_it_is_loaded_beside(tmp_path: Path) -> None:
    two = Two()
    g = two.prior(tmp_path)
    g.check_map(["a", "a", "robot2"], two.stamps_a[[3, 40]].tolist() + [5.0])  # a peer's session is allowed
    with pytest.raises(BackendError, match=r"holds sessions \['monday'\], none of them a session of this graph"):
        g.check_map(["monday"], np.array([T0]))
    with pytest.raises(BackendError, match=r"1 keyframes of session 'a' \(first at stamp 1800000000\.0\) lie "
                                           r"outside its odometry"):
        g.check_map(["a", "a"], np.array([T0 + 1.0, 1.8e9]))


def test_loops_waiting_to_place_a_session_are_saved_and_place_it_after_a_restart(tmp_path: Path) -> None:
    two = Two()
    g = two.prior(tmp_path)
    two.feed_b(g, 40)
    for i in (10, 20):  # two loops: one short of anchoring
        q, m, rel = two.true_loop(i)
        g.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="a")
    assert not g.anchored("b") and g.stats().inter_session[INTER_WAITING] == 2
    g.save(tmp_path / "ab.npz")
    again = PoseGraphBackend.load(tmp_path / "ab.npz")
    assert again.stats().inter_session[INTER_WAITING] == 2 and not again.anchored("b")
    for i in range(40, 60):
        again.add_odometry(float(two.stamps_b[i]), two.odom_b[i], session="b")
    q, m, rel = two.true_loop(50)
    assert again.add_loop(q, m, rel, LOOP_COV, query_session="b", match_session="a")  # the third places it
    assert again.anchored("b") and frame_error(two, again, 59)[0] < 0.3

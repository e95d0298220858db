"""The temporal-consistency gate of VSeq2PC verification: earlier queries must confirm a loop's camera pose."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core.errors import InvalidValueError
from lcpr_core.vseq2pc.consistency import INCONSISTENT, ConsistencyConfig, ConsistencyGate
from lcpr_core.vseq2pc.retrieval import ScanMatch
from lcpr_core.vseq2pc.verify import SequenceVerifier, SequenceVerifyConfig
from lcpr_core.vseq2pc.verify_eval import Accepted, QueryOutcome, Setting, choose, metrics, published

#: a camera looking along the vehicle's x, 0.27 m ahead of it and 0.1 m up (optical frame: z forward)
LIDAR_T_CAM = np.array([[0.0, 0.0, 1.0, 0.27], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0]])


def _pose(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def _candidate(row: int, scan: np.ndarray, world_T_base: np.ndarray, *, verified: bool = True) -> ScanMatch:
    """A candidate whose registration puts the camera at world_T_base @ lidar_T_cam in the map."""
    match_T_query = np.linalg.inv(scan) @ world_T_base @ LIDAR_T_CAM
    return ScanMatch(row=row, id=row, stamp=0.0, pose=scan, logit=0.0, probability=0.5, slice=0, rank=row,
                     verified=verified, fitness=0.8, match_T_query=match_T_query,
                     verification="accepted" if verified else "low overlap")


def _drive(gate: ConsistencyGate, truth: list[np.ndarray], odom: list[np.ndarray]) -> list[bool]:
    """Feed one verified candidate per query (its camera where ``truth`` says); which queries keep it."""
    kept = []
    for world_T_base, odom_T_base in zip(truth, odom, strict=True):
        out = gate.admit(odom_T_base, [_candidate(0, _pose(world_T_base[0, 3] - 3.0), world_T_base)])
        kept.append(out[0].verified)
    return kept


def test_a_loop_is_published_once_the_earlier_queries_confirm_its_camera_pose_through_odometry() -> None:
    truth = [_pose(2.0 * i, 1.0, 10.0) for i in range(5)]
    odom = [_pose(100.0 + 2.0 * i, -50.0, 30.0) for i in range(5)]  # another frame: only relative motion counts
    odom = [odom[0] @ np.linalg.inv(truth[0]) @ t for t in truth]
    gate = ConsistencyGate(ConsistencyConfig(count=3, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    assert _drive(gate, truth, odom) == [False, False, True, True, True]


def test_the_first_confirmed_loop_also_confirms_its_chain_members_once_each_and_late() -> None:
    truth = [_pose(2.0 * i, 1.0, 10.0) for i in range(5)]
    gate = ConsistencyGate(ConsistencyConfig(count=3, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    lates = []
    for q, world_T_base in enumerate(truth):
        scan = _pose(world_T_base[0, 3] - 3.0)
        out, late = gate.admit_all(world_T_base, [_candidate(0, scan, world_T_base)], key=q)
        lates.append(late)
        assert out[0].verified == (q >= 2)
    # query 2 confirms queries 0 and 1 (oldest first); queries 3 and 4 confirm nobody new
    assert [key for key, _ in lates[2]] == [0, 1] and lates[3] == [] and lates[4] == []
    for _, candidates in lates[2]:
        assert candidates[0].verified and candidates[0].verification == "accepted"


def test_a_look_alike_is_never_confirmed_late() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    odom = [_pose(2.0 * i) for i in range(2)]
    gate.admit_all(odom[0], [_candidate(0, _pose(80.0), _pose(85.0))], key="look-alike")  # 83 m off the truth
    out, late = gate.admit_all(odom[1], [_candidate(1, _pose(0.0), _pose(2.0))], key="true")
    assert not out[0].verified and late == []


def test_without_backfill_a_confirmed_loop_confirms_nobody_else() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0, backfill=False), lidar_T_cam=LIDAR_T_CAM)
    gate.admit_all(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0))], key=0)
    out, late = gate.admit_all(_pose(2.0), [_candidate(0, _pose(0.0), _pose(2.0))], key=1)
    assert out[0].verified and late == []


def test_only_the_latest_query_keeps_its_chain_so_the_history_does_not_grow_a_linked_list() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=3, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    for i in range(6):
        gate.admit(_pose(2.0 * i), [_candidate(0, _pose(0.0), _pose(2.0 * i))])
    records = list(gate._history)
    assert not any(isinstance(v, tuple) and any(isinstance(x, type(r)) for x in v)
                   for r in records for v in vars(r).values())  # no record refers to another
    assert len(gate._chain_of_latest) == 2 and all(m in records for m in gate._chain_of_latest)


def test_a_look_alike_place_that_jumps_between_queries_is_refused_as_inconsistent() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    odom = [_pose(2.0 * i) for i in range(3)]
    gate.admit(odom[0], [_candidate(0, _pose(0.0), _pose(0.0))])
    right = _candidate(1, _pose(0.0), _pose(2.0))
    elsewhere = _candidate(2, _pose(80.0), _pose(85.0))  # a look-alike street 83 m away
    out = gate.admit(odom[1], [right, elsewhere])
    assert [c.verified for c in out] == [True, False]
    assert out[1].verification == INCONSISTENT and out[0].verification == "accepted"
    # the look-alike was recorded before the gate, but the next query's true place still chains from the right one
    assert gate.admit(odom[2], [_candidate(1, _pose(0.0), _pose(4.0))])[0].verified


def test_a_query_in_the_chain_without_a_verified_pose_breaks_the_chain() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    gate.admit(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0), verified=False)])
    assert not gate.admit(_pose(2.0), [_candidate(0, _pose(0.0), _pose(2.0))])[0].verified


def test_a_count_of_one_leaves_every_verdict_as_it_was() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=1), lidar_T_cam=LIDAR_T_CAM)
    cands = [_candidate(0, _pose(0.0), _pose(1.0)), _candidate(1, _pose(9.0), _pose(50.0), verified=False)]
    assert gate.admit(_pose(0.0), cands) == cands
    assert gate.admit(None, cands) == cands


def test_chain_members_are_the_latest_queries_at_least_the_spacing_apart() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=5.0, max_m=1.0), lidar_T_cam=LIDAR_T_CAM)
    for i in range(4):  # queries every 1.5 m; the one at 4.5 m verified a pose 3 m off, the one at 0 m the truth
        x = 1.5 * i
        placed = _pose(x + 3.0) if i == 3 else _pose(x)
        gate.admit(_pose(x), [_candidate(0, _pose(0.0), placed)])
    # the query at 6 m: 1.5 m after the wrong one, 6 m after the right one: only the latter is in its chain
    assert gate.admit(_pose(6.0), [_candidate(0, _pose(0.0), _pose(6.0))])[0].verified
    # too far behind (spacing + 10 m of slack): the chain is broken
    gate2 = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=5.0), lidar_T_cam=LIDAR_T_CAM)
    gate2.admit(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0))])
    assert not gate2.admit(_pose(30.0), [_candidate(0, _pose(0.0), _pose(30.0))])[0].verified


@pytest.mark.parametrize("odom", [None, np.full((4, 4), np.nan), np.zeros((4, 4)), np.eye(3)])
def test_missing_or_broken_odometry_refuses_the_loop_and_restarts_the_chain_without_raising(odom: object) -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    gate.admit(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0))])
    out = gate.admit(odom, [_candidate(0, _pose(0.0), _pose(2.0))])  # type: ignore[arg-type]
    assert not out[0].verified and out[0].verification == INCONSISTENT
    assert not gate.admit(_pose(4.0), [_candidate(0, _pose(0.0), _pose(4.0))])[0].verified  # history was dropped


def test_extrinsics_that_are_not_rigid_confirm_nothing_and_raise_nothing() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=2.0 * np.eye(4))
    for x in (0.0, 2.0, 4.0):
        assert not gate.admit(_pose(x), [_candidate(0, _pose(0.0), _pose(x))])[0].verified


def test_a_candidate_without_a_map_pose_cannot_be_confirmed() -> None:
    gate = ConsistencyGate(ConsistencyConfig(count=2, spacing_m=0.0), lidar_T_cam=LIDAR_T_CAM)
    gate.admit(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0))])
    no_pose = ScanMatch(row=0, id=0, stamp=0.0, pose=None, logit=0.0, probability=0.5, slice=0, rank=0,
                        verified=True, fitness=0.8, match_T_query=np.eye(4), verification="accepted")
    assert not gate.admit(_pose(2.0), [no_pose])[0].verified


@pytest.mark.parametrize(("kwargs", "named"), [({"count": 0}, "verify.consistency=0"),
                                               ({"count": 2.5}, "verify.consistency=2.5"),
                                               ({"max_m": 0.0}, "verify.consistency_m=0.0"),
                                               ({"max_deg": float("nan")}, "verify.consistency_deg=nan"),
                                               ({"spacing_m": -1.0}, "verify.consistency_spacing=-1.0")])
def test_a_bad_consistency_setting_is_refused_naming_the_value(kwargs: dict[str, float], named: str) -> None:
    with pytest.raises(InvalidValueError, match=named.replace(".", r"\.")):
        ConsistencyConfig(**kwargs)  # type: ignore[arg-type]


def test_the_verifier_gates_and_reranks_and_a_new_session_drops_the_history() -> None:
    gate = ConsistencyConfig(count=2, spacing_m=0.0)
    verifier = SequenceVerifier(SequenceVerifyConfig(consistency=gate))
    verifier.confirm(_pose(0.0), [_candidate(0, _pose(0.0), _pose(0.0))], lidar_T_cam=LIDAR_T_CAM)
    good = _candidate(1, _pose(0.0), _pose(2.0))
    bad = _candidate(0, _pose(50.0), _pose(60.0))
    out = verifier.confirm(_pose(2.0), [bad, good], lidar_T_cam=LIDAR_T_CAM)
    assert [(c.id, c.verified) for c in out] == [(1, True), (0, False)]
    verifier.restart()
    assert not verifier.confirm(_pose(4.0), [_candidate(1, _pose(0.0), _pose(4.0))],
                                lidar_T_cam=LIDAR_T_CAM)[0].verified


def _outcome(x: float, loop: bool, *accepted: tuple[float, bool, float]) -> QueryOutcome:
    """A query at x; each accepted registration: (fitness, correct, the camera's x in the map)."""
    acc = [Accepted(f, 1, ok, 0.05 if ok else 30.0, 0.1, _pose(cx) @ LIDAR_T_CAM) for f, ok, cx in accepted]
    return QueryOutcome(int(x), loop, None, False, accepted=acc, odom=_pose(x))


def test_the_evaluation_replays_the_gate_so_an_isolated_wrong_loop_is_not_published() -> None:
    outcomes = [_outcome(0.0, True, (0.9, True, 0.0)), _outcome(6.0, True, (0.9, True, 6.0)),
                _outcome(12.0, True, (0.95, False, 60.0), (0.8, True, 12.0)), _outcome(18.0, False),
                _outcome(24.0, True, (0.9, False, 90.0))]
    no_gate = metrics(outcomes, published(outcomes, Setting(1, 0.7, ConsistencyConfig(count=1)),
                                          lidar_T_cam=LIDAR_T_CAM))
    assert (no_gate["published"], no_gate["wrong"]) == (4, 2)
    held = metrics(outcomes, published(outcomes, Setting(1, 0.7, ConsistencyConfig(count=2, backfill=False)),
                                       lidar_T_cam=LIDAR_T_CAM))
    assert (held["published"], held["wrong"], held["precision"]) == (2, 0, 1.0)  # queries at 6 and 12 m
    assert held["recall"] == pytest.approx(2 / 4)
    gated = metrics(outcomes, published(outcomes, Setting(1, 0.7, ConsistencyConfig(count=2)),
                                        lidar_T_cam=LIDAR_T_CAM))
    assert (gated["published"], gated["wrong"], gated["precision"]) == (3, 0, 1.0)  # and the one at 0 m, late
    assert gated["recall"] == pytest.approx(3 / 4)
    sweep = {"lidar_T_cam": LIDAR_T_CAM, "precision": 1.0, "supports": (1,), "tolerances": ((1.0, 3.0),),
             "thresholds": (0.7, 0.75, 0.8)}
    chosen = choose(outcomes, counts=(2, 3), **sweep)  # type: ignore[arg-type]
    # the longer chain closes as many queries once it confirms its members late: ties go to the stricter gate
    assert chosen is not None and chosen.consistency.count == 3 and chosen.min_support == 1
    assert choose(outcomes, counts=(1, 2), **sweep) is None  # type: ignore[arg-type]  # the margin: k=1 is wrong

"""Peer keyframes: another robot's keyframes matched and verified in this detector's map, whichever comes first."""
from __future__ import annotations

import dataclasses
from typing import Any, cast

import numpy as np
import pytest
from test_map_clouds import KeyedDescriber
from test_submap import FIRST_VISIT, MOUNT, RETURN, VERIFY, narrow_frame
from test_verification import pose_error, scene

from lcpr_core.detector import (
    PEER_REFUSALS,
    DetectorConfig,
    LoopDetector,
    MatchConfig,
    PeerKeyframe,
    PeerKeyframeError,
    decode_peer_keyframe,
    encode_peer_keyframe,
)
from lcpr_core.lcpr.describer import Describer
from lcpr_core.lcpr.peers import CLOUD_ENCODINGS
from lcpr_core.verification import SubmapConfig

KEYS = [f"k{i}" for i in range(5)] + ["q0", "q1"]


def keyed_table() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    return {k: (v / np.linalg.norm(v)).astype(np.float32) for k in KEYS for v in [rng.normal(size=256)]}


def robot(session: str, **match: Any) -> LoopDetector:
    options: dict[str, Any] = {"max_distance": 1.0, **match}
    return LoopDetector(DetectorConfig(match=MatchConfig(**options), verify=VERIFY,
                                       submap=SubmapConfig(lidar_xyz=MOUNT), session=session),
                        describer=cast(Describer, KeyedDescriber(keyed_table())))


def drive_first_visit(det: LoopDetector) -> list[int]:
    """Robot a: a 70 deg sensor turning through 180 deg (test_submap's first visit); its keyframe ids."""
    world = scene(1)
    return [det.process(narrow_frame(0.5 * i, f"k{i}", world, T, seed=10 + i)).keyframe_id  # type: ignore[misc]
            for i, T in enumerate(FIRST_VISIT)]


def drive_return(det: LoopDetector) -> list[Any]:
    """Robot b: the return; its last keyframe's descriptor names a's middle keyframe (k2). Its own clock."""
    world = scene(1)
    keys = ["q0", "q1", "k2"]
    return [det.process(narrow_frame(1000.0 + 0.5 * i, keys[i], world, T, seed=30 + i))
            for i, T in enumerate(RETURN)]


def exported(det: LoopDetector, ids: list[int]) -> list[PeerKeyframe]:
    """Each keyframe as the peer would receive it: through the wire record."""
    return [decode_peer_keyframe(encode_peer_keyframe(det.peer_keyframe(i))) for i in ids]


def assert_right_loop(c: Any, *, query_is_b: bool) -> None:
    a_T, b_T = FIRST_VISIT[2], RETURN[2]
    truth = np.linalg.inv(a_T) @ b_T if query_is_b else np.linalg.inv(b_T) @ a_T
    assert c.verified, c.verification
    err_m, err_deg = pose_error(c.match_T_query, truth)
    assert err_m <= 0.05 and err_deg <= 0.5, (err_m, err_deg)


def test_a_loop_between_two_robots_is_found_by_each_whichever_keyframe_arrives_first():
    a, b = robot("a"), robot("b")
    a_ids = drive_first_visit(a)
    b_results = drive_return(b)
    b_ids = [r.keyframe_id for r in b_results]
    assert all(not r.candidates for r in b_results)  # b has not heard of a yet: its own keyframes only
    # b hears a's keyframes after its own return: the pair is found when a's k2 arrives, a's the query
    found_at_b = [b.add_peer_keyframe(kf) for kf in exported(a, a_ids)]
    loops = [r.loop for r in found_at_b if r.loop is not None]
    assert len(loops) == 1 and loops[0].query_id == found_at_b[2].keyframe_id
    assert (loops[0].query_session, loops[0].match_session) == ("a", "b") and loops[0].match_id == b_ids[2]
    assert_right_loop(loops[0], query_is_b=False)
    # a heard b's keyframes late as well; a robot that heard a's keyframes first finds it with b's the query
    c = robot("b")
    for kf in exported(a, a_ids):
        assert c.add_peer_keyframe(kf).candidates == []  # nothing of b's yet; a's own keyframes are never matched
    late = drive_return(c)[-1]
    assert late.loop is not None and (late.loop.query_session, late.loop.match_session) == ("b", "a")
    assert late.loop.match_stamp == 1.0 and late.loop.query_stamp == 1001.0  # a's k2 at its own clock
    assert_right_loop(late.loop, query_is_b=True)
    # and at a: b's keyframes arrive after a's drive, b's the query
    found_at_a = [a.add_peer_keyframe(kf) for kf in exported(b, b_ids)]
    assert found_at_a[2].loop is not None and found_at_a[2].loop.match_id == a_ids[2]
    assert (found_at_a[2].loop.query_session, found_at_a[2].loop.match_session) == ("b", "a")
    assert_right_loop(found_at_a[2].loop, query_is_b=True)


def test_peer_keyframes_interleaved_with_our_own_keep_our_exclusion_window_and_our_submaps():
    a, b = robot("a", exclude_recent_s=30.0), robot("b", exclude_recent_s=30.0)
    a_ids = drive_first_visit(a)
    peers = exported(a, a_ids)
    world = scene(1)
    keys = ["k2", "k2", "k2"]  # b's own keyframes all alike: only the exclusion window keeps them apart
    results = []
    for i, T in enumerate(RETURN):  # a's keyframes arrive between b's own
        b.add_peer_keyframe(peers[i])
        results.append(b.process(narrow_frame(0.5 * i, keys[i], world, T, seed=30 + i)))
    for kf in peers[len(RETURN):]:
        b.add_peer_keyframe(kf)
    # b's own recent keyframes stay hidden from b's queries although a's rows lie between them
    assert [c.match_session for r in results for c in r.candidates] == ["a"]  # a's k2 alone, not b's own
    loop = results[2].loop  # a's k2, stored at row 4 of b's map just before
    assert loop is not None and (loop.match_id, loop.match_stamp, loop.match_session) == (4, 1.0, "a")
    assert_right_loop(loop, query_is_b=True)
    assert b._session_rows == [1, 3, 5]  # noqa: SLF001 - rows between a's
    last = results[2].keyframe_id
    assert last is not None
    window = b._submap_window(last, before_only=True, end=None)  # noqa: SLF001
    assert window is not None and window[0].tolist() == [1, 3, 5]  # b's query stitches b's keyframes only


@pytest.mark.parametrize("change, reason, says", [
    ({"descriptor": np.zeros(128, np.float32)}, "peer: wrong descriptor size", "accepted: (256,) floats"),
    ({"descriptor": np.full(256, np.nan, np.float32)}, "peer: descriptor not finite", "NaN or inf"),
    ({"weights_id": "other"}, "peer: other weights", "'other'; accepted: this detector's 'keyed-test'"),
    ({"session": "a"}, "peer: our own session", "session='a'"),
    ({"session": ""}, "peer: no session name", "accepted: a non-empty name"),
    ({"cloud": np.zeros((10, 4), np.float32)}, "peer: bad cloud", "shape (10, 4)"),
    ({"cloud": np.full((10, 3), 400.0, np.float32)}, "peer: bad cloud", "within 327.67 m"),
    ({"pose": np.ones((4, 4))}, "peer: bad pose", "rigid 4 x 4"),
    ({"stamp": float("nan")}, "peer: bad stamp", "finite time"),
])
def test_a_peer_keyframe_this_detector_cannot_use_is_refused_naming_the_value_and_nothing_changes(
        change: dict[str, Any], reason: str, says: str) -> None:
    a = robot("a")
    drive_first_visit(a)
    good = dataclasses.replace(a.peer_keyframe(2), session="b")
    before = (len(a.map), len(a.map.clouds), a.map.sources)
    result = a.add_peer_keyframe(dataclasses.replace(good, **change))
    assert result.reason == reason and reason in PEER_REFUSALS and result.keyframe_id is None
    assert says in result.errors[0] and not result.candidates
    assert (len(a.map), len(a.map.clouds), a.map.sources) == before
    taken = a.add_peer_keyframe(good)
    assert taken.reason == "peer keyframe" and taken.keyframe_id == 5
    again = a.add_peer_keyframe(good)
    assert again.reason == "peer: already taken" and len(a.map) == 6


def test_an_exported_keyframe_carries_our_session_descriptor_lidar_pose_and_the_stored_cloud():
    a = robot("a")
    ids = drive_first_visit(a)
    kf = a.peer_keyframe(ids[3])
    assert kf.session == "a" and kf.stamp == 1.5 and kf.weights_id == "keyed-test"
    assert np.array_equal(kf.descriptor, keyed_table()["k3"])
    assert kf.pose is not None and np.allclose(kf.pose, FIRST_VISIT[3] @ SubmapConfig(lidar_xyz=MOUNT).base_T_lidar())
    stored = a.map.clouds.get(ids[3])
    assert stored is not None and kf.cloud is not None and np.array_equal(kf.cloud, stored)
    for encoding in CLOUD_ENCODINGS:  # every wire form gives the receiver exactly the stored cloud back
        back = decode_peer_keyframe(encode_peer_keyframe(kf, encoding=encoding))
        assert back.cloud is not None and np.array_equal(back.cloud, stored)
        assert back.pose is not None and np.array_equal(back.pose, kf.pose)
        assert np.array_equal(back.descriptor, kf.descriptor) and (back.session, back.stamp) == ("a", 1.5)


@pytest.mark.parametrize("damage, says", [
    (lambda b: b[:-5], "after its header"),
    (lambda b: b"XXXX" + b[4:], "starts"),
    (lambda b: b[:13] + b"!" + b[14:], "not JSON"),
    (lambda b: b[:20], "header of"),
])
def test_a_damaged_peer_record_is_refused_naming_what_does_not_fit(damage: Any, says: str) -> None:
    a = robot("a")
    drive_first_visit(a)
    data = encode_peer_keyframe(a.peer_keyframe(1))
    with pytest.raises(PeerKeyframeError, match=says):
        decode_peer_keyframe(damage(data))

"""Recall@N and precision-recall on tiny cases worked out by hand."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcpr_core import metrics
from lcpr_core.errors import InputShapeError
from lcpr_core.metrics import plot_pr_curve, precision_recall, recall_at_n

# Database: 4 places on a line, 100 m apart; 1-D descriptors along one axis of 2-D.
DB_POS = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0], [300.0, 0.0]])
DB_DESC = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])


def test_recall_at_1_and_5_counts_true_matches_among_the_top_n() -> None:
    # q0 at place 0, descriptor nearest place 0        -> hit @1
    # q1 at place 1, descriptor nearest place 3, then 2, then 1 -> miss @1, hit @3
    # q2 at place 2, descriptor nearest place 2        -> hit @1
    # q3 far away (no true match)                      -> skipped
    query_pos = np.array([[1.0, 2.0], [101.0, 0.0], [205.0, 3.0], [1000.0, 0.0]])
    query_desc = np.array([[0.1, 0.0], [3.2, 0.0], [2.1, 0.0], [0.0, 0.0]])
    res = recall_at_n(query_desc, DB_DESC, query_pos, DB_POS, n_values=(1, 2, 3, 5), threshold=9.0)
    assert res.num_queries == 3 and res.num_skipped == 1
    assert res.recalls == pytest.approx({1: 2 / 3, 2: 2 / 3, 3: 1.0, 5: 1.0})


def test_recall_uses_every_given_coordinate() -> None:
    db_pos = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 20.0]])
    query_pos = np.array([[0.0, 0.0, 15.0]])  # 15 m from the first, 5 m from the second
    res = recall_at_n(np.array([[0.0]]), np.array([[0.0], [1.0]]), query_pos, db_pos, n_values=(1, 2))
    assert res.recalls == {1: 0.0, 2: 1.0}


def test_recall_without_any_true_match_is_refused() -> None:
    with pytest.raises(ValueError, match="no query has a database entry within 9.0 m"):
        recall_at_n(np.zeros((1, 2)), DB_DESC, np.array([[50.0, 0.0]]), DB_POS)


def test_mismatched_shapes_are_refused_naming_them() -> None:
    with pytest.raises(InputShapeError, match=r"\(2, 3\)"):
        recall_at_n(np.zeros((2, 3)), DB_DESC, np.zeros((2, 2)), DB_POS)
    with pytest.raises(InputShapeError, match="positions"):
        precision_recall(np.zeros((2, 2)), DB_DESC, np.zeros((2, 4)), DB_POS)


def pr_case() -> tuple[np.ndarray, ...]:
    # Top-1 distances and correctness, by construction:
    #   q0: 0.1 correct   q1: 0.2 wrong (true match exists)   q2: 0.3 correct
    #   q3: 0.4 wrong, no true match anywhere
    query_pos = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0], [900.0, 0.0]])
    query_desc = np.array([[0.0, 0.1], [3.0, 0.2], [2.0, 0.3], [1.0, 0.4]])
    return query_desc, DB_DESC, query_pos, DB_POS


def test_precision_recall_sweeps_the_top1_distance_threshold() -> None:
    res = precision_recall(*pr_case(), threshold=9.0)
    assert res.num_queries == 4 and res.num_positives == 3
    np.testing.assert_allclose(res.thresholds, [0.1, 0.2, 0.3, 0.4])
    # t=0.1: TP1 FP0; t=0.2: TP1 FP1; t=0.3: TP2 FP1; t=0.4: TP2 FP2
    np.testing.assert_allclose(res.precision, [1.0, 0.5, 2 / 3, 0.5])
    np.testing.assert_allclose(res.recall, [1 / 3, 1 / 3, 2 / 3, 2 / 3])
    # F1: 0.5, 0.4, 2/3, 4/7 -> max 2/3 at 0.3
    assert res.max_f1 == pytest.approx(2 / 3)
    assert res.max_f1_threshold == pytest.approx(0.3)


def test_equal_top1_distances_form_one_threshold() -> None:
    qd, dd, qp, dp = pr_case()
    qd = qd.copy()
    qd[:, 1] = [0.1, 0.3, 0.3, 0.4]
    res = precision_recall(qd, dd, qp, dp)
    np.testing.assert_allclose(res.thresholds, [0.1, 0.3, 0.4])
    np.testing.assert_allclose(res.precision, [1.0, 2 / 3, 0.5])


def test_the_pr_plot_is_written_as_a_png(tmp_path: Path) -> None:
    path = tmp_path / "plots" / "pr.png"
    plot_pr_curve(precision_recall(*pr_case()), path, title="tiny")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in path.parent.iterdir()] == ["pr.png"]


def test_chunked_recall_and_pr_agree_with_a_plain_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(metrics, "_CHUNK_ELEMENTS", 500)  # several query chunks
    rng = np.random.default_rng(0)
    db_pos, q_pos = rng.uniform(0, 100, (200, 2)), rng.uniform(0, 100, (60, 2))
    db_desc, q_desc = rng.standard_normal((200, 8)), rng.standard_normal((60, 8))
    hits: dict[int, list[bool]] = {1: [], 5: []}
    top1 = []
    for qd, qp in zip(q_desc, q_pos, strict=True):
        near = np.linalg.norm(db_pos - qp, axis=1) <= 9.0
        dist = np.linalg.norm(db_desc - qd, axis=1)
        order = np.argsort(dist)
        top1.append((dist[order[0]], bool(near[order[0]]), bool(near.any())))
        if near.any():
            for n in hits:
                hits[n].append(bool(near[order[:n]].any()))
    res = recall_at_n(q_desc, db_desc, q_pos, db_pos, n_values=(1, 5))
    assert res.num_queries == len(hits[1])
    assert res.recalls == pytest.approx({n: float(np.mean(v)) for n, v in hits.items()})
    pr = precision_recall(q_desc, db_desc, q_pos, db_pos)
    best_t = pr.max_f1_threshold
    tp = sum(ok for d, ok, _ in top1 if d <= best_t)
    fp = sum(not ok for d, ok, _ in top1 if d <= best_t)
    positives = sum(has for _, _, has in top1)
    assert pr.num_positives == positives
    assert pr.max_f1 == pytest.approx(2 * tp / (2 * tp + fp + (positives - tp)))

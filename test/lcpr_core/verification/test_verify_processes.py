"""Candidates verified over worker processes: the same verdicts as in one process, clouds sent once, failures kept."""
from __future__ import annotations

import multiprocessing
import subprocess
import sys
import threading

import numpy as np
import pytest
from test_verify_parallel import same_verdict

from lcpr_core.errors import VerificationError
from lcpr_core.verification import GeometricVerifier, Verification, VerifierConfig
from lcpr_core.verification.processes import CloudRef, VerifierProcesses, _serve, shared_processes
from lcpr_offline.synthetic_scenes import scattered_world, sensor_view

CONFIG = VerifierConfig(num_threads=1)


def _view(world: np.ndarray, x: float, y: float, yaw_deg: float, seed: int) -> np.ndarray:
    """M x 3 compact cloud of what a sensor at (x, y) turned by yaw sees."""
    return GeometricVerifier(CONFIG).compact(sensor_view(world, x, y, yaw_deg, seed=seed))


@pytest.fixture(scope="module")
def clouds() -> dict[str, np.ndarray]:
    """A query, 3 views of its place (moved, turned) and 2 views of other worlds."""
    world = scattered_world(1)
    out = {"query": _view(world, 0.0, 0.0, 0.0, seed=10)}
    for k, (dx, dy, yaw) in enumerate(((1.5, -1.0, 10.0), (-2.0, 2.0, 90.0), (3.0, 0.5, -30.0))):
        out[f"near{k}"] = _view(world, dx, dy, yaw, seed=20 + k)
    for k in range(2):
        out[f"far{k}"] = _view(scattered_world(5 + k), 0.0, 0.0, 0.0, seed=30 + k)
    return out


class Counted:
    """CloudRefs that count how often their points were asked for."""

    def __init__(self, clouds: dict[str, np.ndarray]) -> None:
        self.clouds, self.loads = clouds, dict.fromkeys(clouds, 0)

    def ref(self, name: str) -> CloudRef:
        def load() -> np.ndarray:
            self.loads[name] += 1
            return self.clouds[name]
        return CloudRef(name, load)


MATCHES = ("near0", "far0", "near1", "far1", "near2")


def one_by_one(clouds: dict[str, np.ndarray]) -> list[Verification]:
    """The query's verdict against each of MATCHES, in one process: what the workers must give."""
    verifier = GeometricVerifier(CONFIG)
    query = verifier.prepare(clouds["query"])
    return [verifier.verify_prepared(query, verifier.prepare(clouds[m])) for m in MATCHES]


def test_verdicts_over_two_processes_are_those_of_one_process_and_each_cloud_crosses_once(clouds):
    alone = one_by_one(clouds)
    assert [v.accepted for v in alone] == [True, False, True, False, True]  # the case tells right from wrong
    counted = Counted(clouds)
    with VerifierProcesses(CONFIG, processes=2) as pool:
        first = pool.verify([(counted.ref("query"), counted.ref(m)) for m in MATCHES])
        again = pool.verify([(counted.ref("query"), counted.ref(m)) for m in MATCHES])
        assert pool.fallbacks == 0 and pool.worker_cpu_seconds > 0
    for answers in (first, again):
        assert all(isinstance(v, Verification) and same_verdict(v, a) for v, a in zip(answers, alone, strict=True))
    assert all(counted.loads[m] == 1 for m in MATCHES)  # the second keyframe's clouds were kept by the workers
    assert 1 <= counted.loads["query"] <= 2  # once for each worker given a pair of it


def test_a_pair_whose_cloud_cannot_be_had_is_returned_as_its_error_and_the_others_are_verified(clouds):
    def lost() -> np.ndarray:
        raise VerificationError("keyframe 7 has no cloud")
    query = CloudRef("q", lambda: clouds["query"])
    with VerifierProcesses(CONFIG, processes=2) as pool:
        answers = pool.verify([(query, CloudRef("lost", lost)), (query, CloudRef("near0", lambda: clouds["near0"])),
                               (query, CloudRef("few", lambda: clouds["near0"][:5]))])
        assert pool.fallbacks == 0
    assert isinstance(answers[0], VerificationError) and "keyframe 7" in str(answers[0])
    assert isinstance(answers[1], Verification) and answers[1].accepted
    assert isinstance(answers[2], Verification) and answers[2].reason == "too few points"


def test_a_worker_that_dies_is_stood_in_for_by_the_caller_then_replaced_with_the_same_verdicts(clouds):
    verifier = GeometricVerifier(CONFIG)
    expected = verifier.verify_prepared(verifier.prepare(clouds["query"]), verifier.prepare(clouds["near1"]))
    pool = VerifierProcesses(CONFIG, processes=1)
    try:
        worker = pool._workers[0]
        assert worker is not None
        worker.process.kill()
        worker.process.wait(timeout=10)
        (answer,) = pool.verify([(CloudRef("q", lambda: clouds["query"]), CloudRef("m", lambda: clouds["near1"]))])
        assert isinstance(answer, Verification) and same_verdict(answer, expected)
        assert pool.fallbacks == 1
        (answer,) = pool.verify([(CloudRef("q", lambda: clouds["query"]), CloudRef("m", lambda: clouds["near1"]))])
        assert isinstance(answer, Verification) and same_verdict(answer, expected)
        assert pool.fallbacks == 1 and pool._workers[0] is not None and pool._workers[0] is not worker
    finally:
        pool.close()


def test_tickets_submitted_together_and_collected_in_any_order_get_the_verdicts_of_one_process(clouds):
    alone = one_by_one(clouds)
    counted = Counted(clouds)
    with VerifierProcesses(CONFIG, processes=2) as pool:
        tickets = [pool.submit([(counted.ref("query"), counted.ref(m)) for m in MATCHES[k:]]) for k in range(3)]
        answers = [pool.collect(t) for t in reversed(tickets)][::-1]
        assert pool.fallbacks == 0 and pool.worker_busy_seconds > 0 and all(t.seconds > 0 for t in tickets)
        with pytest.raises(VerificationError, match="collected already"):
            pool.collect(tickets[0])
    for k, got in enumerate(answers):
        assert all(isinstance(v, Verification) and same_verdict(v, a) for v, a in zip(got, alone[k:], strict=True))


def test_pairs_submitted_together_go_to_one_worker_so_their_query_is_prepared_once(clouds):
    alone = one_by_one(clouds)
    counted = Counted(clouds)
    with VerifierProcesses(CONFIG, processes=2) as pool:
        first = pool.submit([(counted.ref("query"), counted.ref(m)) for m in MATCHES], together=True)
        assert len(first.waiting) == 1  # one worker has them all
        second = pool.submit([(counted.ref("far0"), counted.ref(m)) for m in MATCHES[:2]], together=True)
        assert second.waiting and second.waiting != first.waiting  # the idle worker takes the next keyframe
        got = pool.collect(first)
        pool.collect(second)
    assert counted.loads["query"] == 1
    assert all(isinstance(v, Verification) and same_verdict(v, a) for v, a in zip(got, alone, strict=True))


def test_a_worker_is_never_asked_more_than_a_few_requests_ahead_so_its_answers_never_fill_the_socket(clouds):
    from lcpr_core.verification.processes import QUEUED

    verifier = GeometricVerifier(CONFIG)
    expected = verifier.verify_prepared(verifier.prepare(clouds["query"]), verifier.prepare(clouds["near0"]))
    refs = Counted(clouds)
    with VerifierProcesses(CONFIG, processes=1) as pool:
        tickets = []
        for _ in range(3 * QUEUED):
            tickets.append(pool.submit([(refs.ref("query"), refs.ref("near0"))] * 2))
            worker = pool._workers[0]
            assert worker is not None and len(worker.sent) <= QUEUED
        answers = [v for t in tickets for v in pool.collect(t)]
        assert pool.fallbacks == 0
    assert len(answers) == 6 * QUEUED and all(isinstance(v, Verification) and same_verdict(v, expected)
                                              for v in answers)


def test_a_worker_that_dies_with_tickets_in_flight_leaves_their_pairs_to_the_caller_with_the_same_verdicts(clouds):
    verifier = GeometricVerifier(CONFIG)
    expected = [verifier.verify_prepared(verifier.prepare(clouds["query"]), verifier.prepare(clouds[m]))
                for m in MATCHES]
    pool = VerifierProcesses(CONFIG, processes=1)
    try:
        refs = Counted(clouds)
        tickets = [pool.submit([(refs.ref("query"), refs.ref(m))]) for m in MATCHES]
        worker = pool._workers[0]
        assert worker is not None
        worker.process.kill()
        worker.process.wait(timeout=10)
        answers = [pool.collect(t)[0] for t in tickets]
        assert 1 <= pool.fallbacks <= len(MATCHES)  # the ones it had not answered yet
        assert all(isinstance(v, Verification) and same_verdict(v, a) for v, a in zip(answers, expected, strict=True))
        later = pool.collect(pool.submit([(refs.ref("query"), refs.ref("near0"))]))  # a new worker
        assert pool._workers[0] is not None and pool._workers[0] is not worker and isinstance(later[0], Verification)
    finally:
        pool.close()


def test_tickets_still_in_flight_when_the_pool_is_closed_are_verified_by_the_caller(clouds):
    pool = VerifierProcesses(CONFIG, processes=2)
    ticket = pool.submit([(CloudRef("q", lambda: clouds["query"]), CloudRef("m", lambda: clouds["near0"]))])
    pool.close()
    (answer,) = pool.collect(ticket)
    assert isinstance(answer, Verification) and answer.accepted and pool.processes == 0


@pytest.mark.parametrize("processes", [0, -1, 1.5, True, "2"])
def test_a_bad_number_of_processes_is_refused_naming_it(processes):
    with pytest.raises(VerificationError, match="processes=.*accepted"):
        VerifierProcesses(CONFIG, processes=processes)


@pytest.mark.parametrize("processes", [-1, 65, True, 2.0])
def test_a_bad_verify_processes_setting_is_refused_naming_it(processes):
    with pytest.raises(VerificationError, match=r"verify\.processes=.*accepted: an integer 0\.\.64"):
        VerifierConfig(processes=processes)


def test_a_verification_worker_imports_neither_torch_nor_ros():
    code = ("import sys, lcpr_core.verification.processes; "
            "print(sorted(m for m in ('torch', 'rclpy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_callers_asking_for_the_same_settings_share_one_pool_and_other_settings_get_their_own():
    one = shared_processes(CONFIG, processes=1, cache=8)
    assert shared_processes(VerifierConfig(num_threads=1), processes=1, cache=8) is one  # equal settings
    other = shared_processes(VerifierConfig(num_threads=1, min_fitness=0.5), processes=1, cache=8)
    assert other is not one and other.config.min_fitness == 0.5
    one.close()
    assert shared_processes(CONFIG, processes=1, cache=8) is not one  # a closed pool is replaced


def test_a_worker_answers_a_pair_that_raises_with_the_error_and_goes_on_to_the_next():
    parent, child = multiprocessing.Pipe()
    worker = threading.Thread(target=_serve, args=(child,), daemon=True)
    worker.start()
    cloud = GeometricVerifier(CONFIG).compact(_view(scattered_world(1), 0.0, 0.0, 0.0, seed=10))
    parent.send((CONFIG, 4))
    parent.send([(("q", np.asarray(cloud, np.float64)), ("m", np.zeros((10, 2)))),  # 20 numbers: not N x 3
                 (("q", None), ("m2", np.asarray(cloud, np.float64)))])
    answers, cpu_seconds, wall_seconds = parent.recv()
    parent.send(None)
    worker.join(timeout=10)
    assert answers[0][0] == "error" and "ValueError" in answers[0][1]
    assert answers[1][0] == "ok" and answers[1][1].accepted and cpu_seconds >= 0.0 and wall_seconds >= 0.0
    assert not worker.is_alive()

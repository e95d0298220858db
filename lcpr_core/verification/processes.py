"""A keyframe's candidates verified over worker processes: small_gicp holds the GIL, so threads cannot.

    pool = VerifierProcesses(VerifierConfig(), processes=2)
    verdicts = pool.verify([(source, match), ...])   # CloudRef pairs; the same verdicts as in one process
    ticket = pool.submit([(source, match), ...])     # or handed over now, collected later (an evaluation
    verdicts = pool.collect(ticket)                  # keeps the workers busy while it stores the next keyframes)
    pool.close()

Each worker keeps its own cache of prepared clouds (the last ``cache`` match clouds, the last few
sources), and the parent mirrors which keys each worker holds, so a cloud crosses the pipe (and a
submap is stitched) only when the worker it goes to lacks it. Pairs are spread to balance the work:
a pair costs a registration, plus a preparation where its worker lacks a cloud, and a worker still busy
with earlier tickets starts later. A worker answers its requests in the order it got them. Registration
is deterministic, so a verdict does not depend on the worker that made it, nor on when it is collected.
A worker that dies or answers with something unexpected is replaced by verifying in this process when
the ticket is collected (``fallbacks`` counts the pairs).
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
import traceback
import weakref
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import VerificationError
from .config import VerifierConfig
from .verifier import GeometricVerifier, LruCache, PreparedCache, PreparedCloud, Verification

RESPAWNS = 3  # workers replaced after one died, in the life of a pool; then the caller's process verifies
_ONE_THREAD = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
SOURCE_CACHE = 4  # sources (query clouds) each worker keeps: a keyframe's submap and its scan alone, and the last ones
_PREPARE_COST = 0.8  # preparing a cloud, in pair registrations (benchmarks/tools/verify_cost.py)
#: requests a worker may have unanswered: more waits for its oldest answer first. Its answers (about 1 KiB a pair)
#: then always fit the socket's buffer, so a worker never stops reading because its answers go unread.
QUEUED = 4


@dataclass(frozen=True)
class CloudRef:
    """A cloud by key: ``load()`` gives its N x 3 points (called only when a worker lacks the key)."""

    key: Hashable
    load: Callable[[], np.ndarray]


class _Worker:
    """One worker: ``python -m lcpr_core.verification.processes FD``, spoken to over a socket pair. Not
    multiprocessing's spawn, which would run the caller's main script again in the worker."""

    def __init__(self, config: VerifierConfig, cache: int) -> None:
        ours, theirs = socket.socketpair()
        package_root = str(Path(__file__).resolve().parents[2])  # importable from a source checkout too
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            p for p in (package_root, os.environ.get("PYTHONPATH", "")) if p),
            **dict.fromkeys(_ONE_THREAD, "1"))  # the workers are the parallelism: no BLAS threads beside them
        with theirs:
            self.process = subprocess.Popen(  # noqa: S603 - this interpreter, this module, a descriptor number
                [sys.executable, "-m", __name__, str(theirs.fileno())], pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL, env=env, close_fds=True)
        self.conn = Connection(ours.detach())
        self.conn.send((config, cache))
        # the keys its caches hold, touched and filled as the worker's own (the same LRU rule)
        self.sources, self.matches = LruCache[bool](SOURCE_CACHE), LruCache[bool](cache)
        self.sent: deque[tuple[Ticket, list[int], float]] = deque()  # requests unanswered: (ticket, pairs, cost)
        self.backlog = 0.0  # their cost, in pair registrations


@dataclass(eq=False)
class Ticket:
    """Pairs handed to the workers by :meth:`VerifierProcesses.submit`; :meth:`VerifierProcesses.collect` gives
    their verdicts."""

    pairs: list[tuple[CloudRef, CloudRef]]
    verdicts: list[Verification | Exception | None]  # filled in as the workers answer; None: not yet
    waiting: set[int] = field(default_factory=set)  # the workers whose answer is still to come
    #: wall seconds of its verification as if it ran alone: the slowest worker's share (not the time it waited
    #: behind earlier tickets), plus the pairs verified in the caller's process
    seconds: float = 0.0
    collected: bool = False


class VerifierProcesses:
    """``processes`` worker processes verifying pairs of clouds with one :class:`VerifierConfig`."""

    def __init__(self, config: VerifierConfig, *, processes: int, cache: int = 64) -> None:
        if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
            raise VerificationError(f"verify processes={processes!r}; accepted: an integer >= 1")
        self.config = config
        self.fallbacks = 0  # pairs verified in this process because a worker failed
        self.worker_cpu_seconds = 0.0  # CPU time the workers spent on requests, all of them together
        self.worker_busy_seconds = 0.0  # wall time the workers spent on requests, all of them together
        self._local = GeometricVerifier(config)
        self._lock = threading.Lock()
        self._cache, self._respawns = cache, RESPAWNS
        self._workers: list[_Worker | None] = [_Worker(config, cache) for _ in range(processes)]
        self._finalizer = weakref.finalize(self, _stop, self._workers)  # the list itself: respawned ones too

    @property
    def processes(self) -> int:
        return len(self._workers)

    @property
    def pids(self) -> list[int]:
        """The running workers' process ids (to watch their memory, for instance)."""
        return [w.process.pid for w in self._workers if w is not None]

    def verify(self, pairs: Sequence[tuple[CloudRef, CloudRef]]) -> list[Verification | Exception]:
        """Each (source, match) pair's verdict, in order; an exception raised verifying a pair is returned in its
        place (the caller decides what a failed pair means)."""
        return self.collect(self.submit(pairs))

    def submit(self, pairs: Sequence[tuple[CloudRef, CloudRef]], *, together: bool = False) -> Ticket:
        """Hand the pairs to the workers and return at once (their clouds are loaded now, where a worker lacks
        them); :meth:`collect` gives the verdicts, those :meth:`verify` would have given. Tickets may be
        collected in any order; each worker works through its requests in the order they were submitted.
        ``together``: all of them to the one worker that finishes them soonest (throughput: a query cloud is
        prepared once, where spreading the pairs prepares it in every worker they go to, for less latency)."""
        with self._lock:
            for w, worker in enumerate(self._workers):
                if worker is None and self._respawns > 0:
                    self._respawns -= 1
                    self._workers[w] = _Worker(self.config, self._cache)
            self._drain()  # answers already there: the workers' backlogs as they are now
            ticket = Ticket(list(pairs), [None] * len(pairs))
            for w, (indices, cost) in self._assign(ticket.pairs, together=together).items():
                while (worker := self._workers[w]) is not None and len(worker.sent) >= QUEUED:
                    self._receive(w)
                if worker is None:  # it failed meanwhile: its pairs are verified here when collected
                    continue
                request, given = [], []
                for i in indices:
                    try:
                        request.append(self._request(worker, ticket.pairs[i]))
                        given.append(i)
                    except Exception as err:  # noqa: BLE001 - a cloud that cannot be loaded fails its pair only
                        ticket.verdicts[i] = err
                try:
                    worker.conn.send(request)
                except (OSError, ValueError, EOFError):
                    self._drop(w)
                    continue
                worker.sent.append((ticket, given, cost))
                worker.backlog += cost
                ticket.waiting.add(w)
            return ticket

    def collect(self, ticket: Ticket) -> list[Verification | Exception]:
        """The verdicts of a :meth:`submit`'s pairs, in order, waiting for the workers' answers; the pairs of a
        worker that failed are verified here."""
        with self._lock:
            if ticket.collected:
                raise VerificationError("this ticket's verdicts were collected already; accepted: a ticket once")
            while ticket.waiting:
                w = min(ticket.waiting)
                self._receive(w)  # the worker's next answer: this ticket's or an earlier one's
                worker = self._workers[w] if w < len(self._workers) else None
                if worker is None or not worker.sent:  # nothing more will come from it
                    ticket.waiting.discard(w)
            tic = time.perf_counter()
            for i, verdict in enumerate(ticket.verdicts):
                if verdict is None:  # its worker failed, or it lacked a cloud it should have had
                    self.fallbacks += 1
                    ticket.verdicts[i] = self._verify_here(*ticket.pairs[i])
            ticket.seconds += time.perf_counter() - tic
            ticket.collected = True
            return [v for v in ticket.verdicts if v is not None]

    def close(self) -> None:
        """Stop the workers (also done when this object is collected or the interpreter exits); the pairs of tickets
        not yet collected are then verified in this process when they are."""
        with self._lock:
            for w in range(len(self._workers)):
                self._forget(w)
            self._finalizer()
            self._workers.clear()

    def __enter__(self) -> VerifierProcesses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the parent's side ---------------------------------------------------------------------
    def _assign(self, pairs: Sequence[tuple[CloudRef, CloudRef]], *, together: bool = False
                ) -> dict[int, tuple[list[int], float]]:
        """Worker index -> (the pairs it verifies, their cost): greedily the worker that finishes the pair soonest
        (``together``: all the pairs), counting its backlog of earlier tickets, a registration per pair and a
        preparation for each cloud the worker lacks."""
        alive = {w: worker for w, worker in enumerate(self._workers) if worker is not None}
        load = {w: worker.backlog for w, worker in alive.items()}
        sources: dict[int, set[Hashable]] = {w: set() for w in alive}  # sources given to a worker in this plan
        plan: dict[int, tuple[list[int], float]] = {}
        if together and alive:
            sources_of, matches_of = {s.key for s, _ in pairs}, {m.key for _, m in pairs}
            whole = {w: len(pairs) + _PREPARE_COST * (len(sources_of - set(worker.sources))
                                                      + len(matches_of - set(worker.matches)))
                     for w, worker in alive.items()}
            w = min(alive, key=lambda w: (load[w] + whole[w], w))
            return {w: (list(range(len(pairs))), whole[w])} if pairs else {}
        for i, (source, match) in enumerate(pairs):
            if not alive:
                break
            finish = {w: load[w] + 1.0 + _PREPARE_COST * (
                (source.key not in worker.sources and source.key not in sources[w]) + (match.key not in worker.matches))
                for w, worker in alive.items()}
            w = min(finish, key=lambda w: (finish[w], w))
            indices, cost = plan.get(w, ([], 0.0))
            plan[w] = ([*indices, i], cost + finish[w] - load[w])
            load[w] = finish[w]
            sources[w].add(source.key)
        return plan

    def _request(self, worker: _Worker, pair: tuple[CloudRef, CloudRef]) -> tuple[tuple[Hashable, Any], ...]:
        """What the worker needs for a pair: each key, with its points where the worker lacks them (loaded before
        the mirror of its cache changes: a load that raises leaves the mirror as it was)."""
        sides = ((pair[0], pair[0].key in worker.sources), (pair[1], pair[1].key in worker.matches))
        xyz = [None if held else np.ascontiguousarray(ref.load(), np.float64).reshape(-1, 3) for ref, held in sides]
        for (ref, held), keys in zip(sides, (worker.sources, worker.matches), strict=True):
            if held:
                keys.get(ref.key)
            else:
                keys.put(ref.key, True)
        return tuple((ref.key, points) for (ref, _), points in zip(sides, xyz, strict=True))

    def _settle(self, worker: _Worker, pair: tuple[CloudRef, CloudRef], answer: Any
                ) -> Verification | Exception | None:
        """A worker's answer for one pair; None where it must be verified here."""
        kind, value = answer
        if kind == "ok" and isinstance(value, Verification):
            return value
        if kind == "missing":  # its cache and the mirror disagree: forget the key, so the next request sends it
            worker.sources.discard(pair[0].key)
            worker.matches.discard(pair[1].key)
            return None
        if kind == "error":  # the pair raised (as it would here); the cloud it failed to prepare is not kept
            worker.sources.discard(pair[0].key)
            worker.matches.discard(pair[1].key)
            return VerificationError(str(value))
        return None

    def _verify_here(self, source: CloudRef, match: CloudRef) -> Verification | Exception:
        try:
            verifier = self._local
            return verifier.verify_prepared(verifier.prepare(source.load()), verifier.prepare(match.load()))
        except Exception as err:  # noqa: BLE001 - returned in the pair's place, as a worker's would be
            return err

    def _receive(self, w: int) -> None:
        """Worker ``w``'s next answer, waited for, given to the ticket of its oldest request."""
        worker = self._workers[w] if w < len(self._workers) else None
        if worker is None or not worker.sent:  # gone (its tickets were told), or nothing asked of it
            return
        try:
            answers, cpu_seconds, wall_seconds = worker.conn.recv()
            ticket, indices, cost = worker.sent[0]
            understood = len(answers) == len(indices)  # else it answered something else: no longer to be trusted
        except (OSError, EOFError, ValueError, TypeError):
            understood = False
        if not understood:
            self._drop(w)
            return
        worker.sent.popleft()
        worker.backlog = max(worker.backlog - cost, 0.0) if worker.sent else 0.0
        self.worker_cpu_seconds += cpu_seconds
        self.worker_busy_seconds += wall_seconds
        ticket.seconds = max(ticket.seconds, wall_seconds)
        ticket.waiting.discard(w)
        for i, answer in zip(indices, answers, strict=True):
            ticket.verdicts[i] = self._settle(worker, ticket.pairs[i], answer)

    def _drain(self) -> None:
        """Take the answers that have arrived, without waiting (a worker whose answers pile up unread would stop
        reading requests)."""
        for w, worker in enumerate(self._workers):
            try:
                while worker is not None and worker.sent and worker.conn.poll(0):
                    self._receive(w)
                    worker = self._workers[w]
            except (OSError, EOFError, ValueError):
                self._drop(w)

    def _forget(self, w: int) -> None:
        """Worker ``w``'s unanswered requests are left to the caller's process (verified when collected)."""
        worker = self._workers[w]
        if worker is not None:
            for ticket, _, _ in worker.sent:
                ticket.waiting.discard(w)
            worker.sent.clear()
            worker.backlog = 0.0

    def _drop(self, w: int) -> None:
        worker = self._workers[w]
        self._forget(w)
        self._workers[w] = None
        if worker is not None:
            _stop([worker])


_SHARED: OrderedDict[tuple[VerifierConfig, int, int], VerifierProcesses] = OrderedDict()
_SHARED_POOLS = 2  # pools kept for reuse (a pool whose last user lets go of it stops its workers)
_SHARED_LOCK = threading.Lock()


def shared_processes(config: VerifierConfig, *, processes: int, cache: int = 64) -> VerifierProcesses:
    """A pool for these settings, shared by every caller in this process that asks for the same ones: detectors
    made one after another (an evaluation, a test suite, a node whose settings change back) start no new workers.
    Callers sharing a pool must keep their cloud keys apart (e.g. a per-caller first element)."""
    key = (config, processes, cache)
    with _SHARED_LOCK:
        pool = _SHARED.get(key)
        if pool is None or not pool.processes:
            pool = _SHARED[key] = VerifierProcesses(config, processes=processes, cache=cache)
        _SHARED.move_to_end(key)
        while len(_SHARED) > _SHARED_POOLS:
            _SHARED.popitem(last=False)
        return pool


def _stop(workers: list[_Worker | None]) -> None:
    for worker in workers:
        if worker is None:
            continue
        try:
            worker.conn.send(None)
        except (OSError, ValueError):
            pass
        worker.conn.close()
        try:
            worker.process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            worker.process.kill()
            worker.process.wait(timeout=2.0)


def _serve(conn: Connection) -> None:
    """A worker's loop: (config, cache size) first; then a list of pairs in, (a list of ("ok", Verification) /
    ("error", text) / ("missing", key), the request's CPU seconds, its wall seconds) out; None stops it."""
    try:
        config, cache = conn.recv()
    except (EOFError, OSError):
        return
    verifier = GeometricVerifier(config)
    sources, matches = PreparedCache(SOURCE_CACHE), PreparedCache(cache)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        cpu, wall = time.process_time(), time.perf_counter()
        answers: list[tuple[str, Any]] = []
        for (skey, sxyz), (mkey, mxyz) in request:
            try:
                source = _cloud(verifier, sources, skey, sxyz)
                match = _cloud(verifier, matches, mkey, mxyz)
                if source is None or match is None:
                    answers.append(("missing", skey if source is None else mkey))
                    continue
                answers.append(("ok", verifier.verify_prepared(source, match)))
            except Exception as err:  # noqa: BLE001 - one pair's failure is its answer, the worker goes on
                answers.append(("error", f"{type(err).__name__}: {err}"
                                if str(err) else traceback.format_exception_only(err)[-1].strip()))
        try:
            conn.send((answers, time.process_time() - cpu, time.perf_counter() - wall))
        except (OSError, ValueError):
            return


def _cloud(verifier: GeometricVerifier, cache: PreparedCache, key: Hashable, xyz: np.ndarray | None
           ) -> PreparedCloud | None:
    if xyz is None:
        return cache.get(key)
    return cache.put(key, verifier.prepare(xyz))


if __name__ == "__main__":  # a worker: the socket's descriptor number is the one argument
    _serve(Connection(int(sys.argv[1])))

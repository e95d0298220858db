"""The node's health -> diagnostic_msgs/DiagnosticArray (two statuses: inputs and detector).

Keys are stable so that tools and tests can read them: ``rate <stream> (Hz)``,
``dropped <reason>``, ``stopped cameras``, ``frames without <topic>``,
``latency p50/p90/p99 (ms)``, ``model p50/p90/p99 (ms)``, ``map size`` ...
A status is WARN while a camera is stopped or when drops grew since the last report.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

HARDWARE_ID = "lcpr"


@dataclass
class Health:
    rates: dict[str, float] = field(default_factory=dict)  # stream -> Hz
    totals: dict[str, int] = field(default_factory=dict)  # stream -> messages received
    drops: dict[str, int] = field(default_factory=dict)  # reason -> messages or frames dropped
    fixes: dict[str, int] = field(default_factory=dict)  # reason -> repaired (e.g. NaN points removed)
    decisions: dict[str, int] = field(default_factory=dict)  # detector reason -> frames
    stopped: list[str] = field(default_factory=list)  # camera topics stopped now
    missing: dict[str, int] = field(default_factory=dict)  # camera topic -> frames without it
    warnings: list[str] = field(default_factory=list)  # causes warned about so far
    latency: list[float] | None = None  # p50, p90, p99 s: cloud arrival -> result published
    model: list[float] | None = None  # p50, p90, p99 s: preprocessing + network
    map_size: int = 0
    session_keyframes: int = 0
    loops: int = 0  # loops published on ~/loop_closure
    verification: dict[str, int] = field(default_factory=dict)  # verdict ("accepted", reasons) -> candidates
    verify_time: list[float] | None = None  # p50, p90, p99 s: verification of one keyframe's candidates
    sync_pending: int = 0
    worker_waiting: int = 0
    worker_busy: bool = False
    inference: str = ""  # the inference path in use (model.precision, or what auto chose)
    runtime: str = ""  # what runs it: torch, onnxruntime or openvino


def _kv(key: str, value: object) -> KeyValue:
    return KeyValue(key=key, value=str(value))


def _ms(values: list[float] | None) -> list[str]:
    return ["n/a"] * 3 if values is None else [f"{v * 1000:.1f}" for v in values]


class DiagnosticsBuilder:
    """Turns successive :class:`Health` snapshots into messages (remembers drops already reported)."""

    def __init__(self, node_name: str) -> None:
        self._name = node_name
        self._reported_drops = 0

    def build(self, health: Health, sec: int, nanosec: int) -> DiagnosticArray:
        msg = DiagnosticArray()
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.status = [self._inputs(health), self._detector(health)]
        return msg

    def _inputs(self, h: Health) -> DiagnosticStatus:
        total_drops = sum(h.drops.values())
        new_drops, self._reported_drops = total_drops - self._reported_drops, total_drops
        problems = []
        if h.stopped:
            problems.append(f"cameras stopped: {', '.join(h.stopped)}")
        if new_drops:
            problems.append(f"{new_drops} dropped since last report")
        values = [_kv(f"rate {s} (Hz)", f"{r:.2f}") for s, r in sorted(h.rates.items())]
        values += [_kv(f"received {s}", n) for s, n in sorted(h.totals.items())]
        values += [_kv(f"dropped {reason}", n) for reason, n in sorted(h.drops.items())]
        values += [_kv(reason, n) for reason, n in sorted(h.fixes.items())]
        values += [_kv("stopped cameras", ",".join(h.stopped)), _kv("degraded", int(bool(h.stopped)))]
        values += [_kv(f"frames without {topic}", n) for topic, n in h.missing.items()]
        values += [_kv("warnings", "; ".join(h.warnings))]
        return DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
            name=f"{self._name}: inputs", hardware_id=HARDWARE_ID,
            message="; ".join(problems) or "ok", values=values,
        )

    def _detector(self, h: Health) -> DiagnosticStatus:
        lat, model = _ms(h.latency), _ms(h.model)
        values = [
            _kv("map size", h.map_size),
            _kv("session keyframes", h.session_keyframes),
            _kv("loops", h.loops),
            *([_kv("inference path", h.inference)] if h.inference else []),
            *([_kv("inference runtime", h.runtime)] if h.runtime else []),
            *[_kv(f"latency {p} (ms)", v) for p, v in zip(("p50", "p90", "p99"), lat, strict=False)],
            *[_kv(f"model {p} (ms)", v) for p, v in zip(("p50", "p90", "p99"), model, strict=False)],
            *[_kv(f"verify {p} (ms)", v) for p, v in zip(("p50", "p90", "p99"), _ms(h.verify_time), strict=False)],
            _kv("candidates verified", h.verification.get("accepted", 0)),
            _kv("candidates rejected", sum(n for k, n in h.verification.items() if k != "accepted")),
            *[_kv(f"rejected {reason}", n) for reason, n in sorted(h.verification.items()) if reason != "accepted"],
            _kv("sync pending", h.sync_pending),
            _kv("worker waiting", h.worker_waiting),
            _kv("worker busy", int(h.worker_busy)),
            *[_kv(f"frames {reason}", n) for reason, n in sorted(h.decisions.items())],
        ]
        return DiagnosticStatus(
            level=DiagnosticStatus.OK, name=f"{self._name}: detector", hardware_id=HARDWARE_ID,
            message=f"{h.map_size} places, latency p50 {lat[0]} ms", values=values,
        )

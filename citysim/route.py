"""Street graphs, drives with revisits, the KITTI-00 trajectory, keyframe sampling, revisit counts."""
from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path as FsPath

import numpy as np

from .ground import LANE_WIDTH, PARKING_WIDTH
from .hashing import drive_keys, rng_for

Node = tuple[int, int]


@dataclass(frozen=True)
class StreetSpec:
    """Cross-section of one street."""

    lanes: int  # per direction
    parking: bool
    sidewalk: float  # metres, each side
    trees: bool

    @property
    def half_width(self) -> float:
        """Centre line to kerb, metres."""
        return self.lanes * LANE_WIDTH + (PARKING_WIDTH if self.parking else 0.0)


@dataclass
class StreetGraph:
    """A jittered grid of intersections; streets along rows (j) and columns (i).

    Only ``drivable`` nodes (all but the outer ring) are used by drives, so the city
    extends beyond the streets a drive can reach.
    """

    nodes: np.ndarray  # nx x ny x 2 positions
    rows: list[StreetSpec]  # street along constant j
    cols: list[StreetSpec]  # street along constant i

    @property
    def shape(self) -> tuple[int, int]:
        return self.nodes.shape[0], self.nodes.shape[1]

    def pos(self, n: Node) -> np.ndarray:
        return self.nodes[n[0], n[1]]

    def spec(self, a: Node, b: Node) -> StreetSpec:
        return self.rows[a[1]] if a[1] == b[1] else self.cols[a[0]]

    def drivable(self, n: Node) -> bool:
        nx, ny = self.shape
        return 1 <= n[0] <= nx - 2 and 1 <= n[1] <= ny - 2

    def neighbours(self, n: Node, *, drivable: bool = True) -> list[Node]:
        nx, ny = self.shape
        out = []
        for di, dj in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            m = (n[0] + di, n[1] + dj)
            if 0 <= m[0] < nx and 0 <= m[1] < ny and (not drivable or self.drivable(m)):
                out.append(m)
        return out

    def edges(self) -> list[tuple[Node, Node]]:
        """Every street piece between neighbouring nodes, once."""
        nx, ny = self.shape
        out = [((i, j), (i + 1, j)) for j in range(ny) for i in range(nx - 1)]
        return out + [((i, j), (i, j + 1)) for i in range(nx) for j in range(ny - 1)]

    def length(self, a: Node, b: Node) -> float:
        return float(np.hypot(*(self.pos(b) - self.pos(a))))


def make_street_graph(*, seed: int, inner: tuple[int, int], block_min: float = 70.0, block_max: float = 130.0,
                      jitter: float = 3.0) -> StreetGraph:
    """A grid with ``inner`` drivable blocks in x and y plus one outer ring of blocks."""
    if min(inner) < 1:
        raise ValueError(f"inner={inner}: need at least 1 x 1 drivable blocks")
    rng = rng_for(seed, 1)
    nx, ny = inner[0] + 3, inner[1] + 3
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(block_min, block_max, nx - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(block_min, block_max, ny - 1))])
    xs -= xs[nx // 2]
    ys -= ys[ny // 2]
    nodes = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    nodes = nodes + rng.uniform(-jitter, jitter, nodes.shape)

    def spec() -> StreetSpec:
        lanes = 2 if rng.uniform() < 0.35 else 1
        return StreetSpec(lanes=lanes, parking=bool(rng.uniform() < 0.75), sidewalk=float(rng.uniform(2.5, 5.0)),
                          trees=bool(rng.uniform() < 0.6))

    return StreetGraph(nodes=nodes, rows=[spec() for _ in range(ny)], cols=[spec() for _ in range(nx)])


@dataclass
class Path:
    """A dense driven path: positions, headings, arc length and time."""

    xy: np.ndarray  # N x 2
    yaw: np.ndarray  # N, radians (unwrapped)
    s: np.ndarray  # N, metres, strictly increasing
    t: np.ndarray  # N, seconds from the start

    @property
    def length(self) -> float:
        return float(self.s[-1] - self.s[0])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Interpolated (xy M x 2, yaw M, t M) at arc lengths s."""
        s = np.asarray(s, dtype=np.float64)
        xy = np.stack([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])], axis=1)
        return xy, np.interp(s, self.s, self.yaw), np.interp(s, self.s, self.t)


@dataclass
class Keyframes:
    """Poses at which frames are rendered."""

    xy: np.ndarray  # N x 2
    yaw: np.ndarray  # N
    stamps: np.ndarray  # N, seconds (absolute)
    s: np.ndarray  # N arc length

    def __len__(self) -> int:
        return int(self.xy.shape[0])


# ----------------------------------------------------------------------------- grid drives


def _directed_shortest(graph: StreetGraph, start: tuple[Node, Node], goal: tuple[Node, Node]) -> list[Node]:
    """Nodes after start[1] up to goal[1], over directed edges without U-turns (Dijkstra)."""
    dist = {start: 0.0}
    prev: dict[tuple[Node, Node], tuple[Node, Node]] = {}
    heap = [(0.0, start)]
    while heap:
        d, e = heapq.heappop(heap)
        if e == goal:
            break
        if d > dist.get(e, np.inf):
            continue
        u, v = e
        nbrs = [w for w in graph.neighbours(v) if w != u] or [u]
        for w in nbrs:
            nd = d + graph.length(v, w)
            f = (v, w)
            if nd < dist.get(f, np.inf):
                dist[f], prev[f] = nd, e
                heapq.heappush(heap, (nd, f))
    if goal not in dist:
        raise ValueError(f"street graph: no route from {start} to {goal}")
    out, e = [], goal
    while e != start:
        out.append(e[1])
        e = prev[e]
    return out[::-1]


def plan_grid_nodes(graph: StreetGraph, *, length_m: float, seed: int, min_age_m: float = 350.0,
                    drive: int = 0, variant: int = 0) -> list[Node]:
    """A node sequence at least ``length_m`` long that explores and replays earlier stretches.

    After a short exploration, the drive repeatedly goes back to a stretch of 2-3 streets
    driven at least ``min_age_m`` metres earlier (so well over 30 s at city speed) and
    drives it again, alternately in the same and in the opposite direction; the way there
    often closes a loop as well. U-turns are never made. Drive ``drive`` > 0 of the same
    seed starts on one of drive 0's streets (either way, not at drive 0's start node) and
    makes its own random choices, so drives of one city share streets; ``variant`` > 0 gives
    the same drive another plan.
    """
    rng = rng_for(seed, 2, *drive_keys(drive, variant=variant))
    if drive == 0:
        nx, ny = graph.shape
        inner = [(i, j) for i in range(1, nx - 1) for j in range(1, ny - 1)]
        start = inner[int(rng.integers(len(inner)))]
        first = graph.neighbours(start)
        nodes = [start, first[int(rng.integers(len(first)))]]
    else:  # on a street of drive 0, either way, but not from drive 0's start: the drives share ground
        nodes0 = plan_grid_nodes(graph, length_m=length_m, seed=seed, min_age_m=min_age_m)
        cum0 = np.cumsum([graph.length(a, b) for a, b in zip(nodes0[:-1], nodes0[1:], strict=True)])
        done = max(int(np.searchsorted(cum0, length_m - 100.0, side="right")), 1)  # well inside drive 0
        pairs = list(zip(nodes0[:done], nodes0[1:done + 1], strict=True))
        starts = [(a, b) for a, b in pairs + [(b, a) for a, b in pairs] if a != nodes0[0]]
        nodes = list(starts[int(rng.integers(len(starts)))])
    cum = [0.0, graph.length(nodes[0], nodes[1])]  # distance driven when reaching nodes[i]
    visits: dict[tuple[Node, Node], int] = {}
    explore_left, opposite = int(rng.integers(3, 5)), bool(rng.uniform() < 0.5)
    while cum[-1] < length_m:
        u, v = nodes[-2], nodes[-1]
        m = int(rng.integers(2, 4))
        old = [k for k in range(len(nodes) - m) if cum[k + m] <= cum[-1] - min_age_m]
        if explore_left > 0 or not old:
            options = [w for w in graph.neighbours(v) if w != u] or [u]
            weights = np.array([1.0 / (1.0 + 3.0 * (visits.get((v, w), 0) + visits.get((w, v), 0))) for w in options])
            step = [options[int(rng.choice(len(options), p=weights / weights.sum()))]]
            explore_left -= 1
        else:
            best = None
            for k in rng.permutation(old)[:8]:  # of a few old stretches, the one reached soonest
                stretch = nodes[k:k + m + 1][::-1] if opposite else nodes[k:k + m + 1]
                approach = _directed_shortest(graph, (u, v), (stretch[0], stretch[1]))
                cost = sum(graph.length(a, b) for a, b in zip([v] + approach[:-1], approach, strict=False))
                if best is None or cost < best[0]:
                    best = (cost, approach + stretch[2:])
            assert best is not None  # old is not empty in this branch
            step = best[1]
            opposite = not opposite
            explore_left = int(rng.integers(0, 2))
        for w in step:
            a = nodes[-1]
            visits[(a, w)] = visits.get((a, w), 0) + 1
            cum.append(cum[-1] + graph.length(a, w))
            nodes.append(w)
    return nodes


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _smooth_step(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def grid_path(graph: StreetGraph, nodes: list[Node], *, seed: int, speed: float = 10.0, step: float = 0.5,
              drive: int = 0) -> Path:
    """Dense path along a node sequence: right-hand lanes, lane changes, rounded corners, speed profile.

    ``drive`` picks the random stream of lanes and speeds (0: a city's first drive).
    """
    rng = rng_for(seed, 3, *drive_keys(drive))
    pieces: list[np.ndarray] = []
    lane = 0
    dirs = [graph.pos(b) - graph.pos(a) for a, b in zip(nodes[:-1], nodes[1:], strict=True)]
    dirs = [d / np.hypot(*d) for d in dirs]
    for k, (a, b) in enumerate(zip(nodes[:-1], nodes[1:], strict=True)):
        spec = graph.spec(a, b)
        pa, pb = graph.pos(a), graph.pos(b)
        length = float(np.hypot(*(pb - pa)))
        u = dirs[k]
        right = np.array([u[1], -u[0]])
        turn_in = k > 0 and abs(_cross(dirs[k - 1], u)) > 0.3
        turn_out = k + 1 < len(dirs) and abs(_cross(u, dirs[k + 1])) > 0.3
        c0 = 0.0 if k == 0 else (13.0 if turn_in else 4.0)
        c1 = 0.0 if k + 1 == len(dirs) else (13.0 if turn_out else 4.0)
        lane = min(lane, spec.lanes - 1)
        if rng.uniform() < 0.5:
            lane = int(rng.integers(spec.lanes))
        lane_end = int(rng.integers(spec.lanes)) if rng.uniform() < 0.4 else lane
        s = np.arange(c0, length - c1 + 1e-9, step)
        mid, span = rng.uniform(0.3, 0.7) * length, 30.0
        blend = _smooth_step((s - mid) / span + 0.5)
        wander = 0.25 * np.sin(s / rng.uniform(25, 60) + rng.uniform(0, 2 * np.pi))
        offset = (lane + 0.5 + (lane_end - lane) * blend) * LANE_WIDTH + wander
        pts = pa[None, :] + s[:, None] * u[None, :] + offset[:, None] * right[None, :]
        if pieces:
            p_end, d_end = pieces[-1][-1], dirs[k - 1]
            q = pts[0]
            cross = _cross(d_end, u)
            gap = float(np.hypot(*(q - p_end)))
            ctrl = 0.5 * (p_end + q)
            if abs(cross) > 0.3:  # a turn: the control point is where the two lane lines meet
                alpha = _cross(q - p_end, u) / cross
                if 0.0 < alpha < 1.5 * gap:
                    ctrl = p_end + alpha * d_end
            n = max(int(np.hypot(*(q - p_end)) / step), 2)
            w = np.linspace(0, 1, n + 1)[1:-1, None]
            pieces.append((1 - w) ** 2 * p_end + 2 * (1 - w) * w * ctrl + w ** 2 * q)
        pieces.append(pts)
        lane = lane_end
    return path_from_points(np.concatenate(pieces), speed=speed, seed=seed, step=step, drive=drive)


def path_from_points(points: np.ndarray, *, speed: float, seed: int, step: float = 0.5, drive: int = 0) -> Path:
    """Resample points uniformly by arc length; headings from the tangent; time from a speed profile.

    ``drive`` picks the random stream of the speed profile (0: a city's first drive).
    """
    seg = np.hypot(*np.diff(points, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-6])
    s, points = s[keep], points[keep]
    su = np.arange(0.0, s[-1], step)
    xy = np.stack([np.interp(su, s, points[:, 0]), np.interp(su, s, points[:, 1])], axis=1)
    d = np.gradient(xy, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    curvature = np.abs(np.gradient(yaw, su))
    curvature = np.convolve(curvature, np.ones(9) / 9, mode="same")
    rng = rng_for(seed, 4, *drive_keys(drive))
    cruise = speed * (1.0 + 0.15 * np.sin(su / rng.uniform(150, 300) + rng.uniform(0, 2 * np.pi)))
    v = np.minimum(cruise, np.sqrt(2.5 / np.maximum(curvature, 1e-6)))
    v = np.maximum(v, 2.5)
    for i in range(1, len(v)):  # accelerate at most 1.5 m/s^2
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 3.0 * step))
    for i in range(len(v) - 2, -1, -1):  # brake at most 2 m/s^2
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 4.0 * step))
    t = np.concatenate([[0.0], np.cumsum(step / (0.5 * (v[1:] + v[:-1])))])
    return Path(xy=xy, yaw=yaw, s=su, t=t)


# ----------------------------------------------------------------------------- KITTI trajectory


def load_kitti_poses(path: str | FsPath) -> np.ndarray:
    """KITTI odometry poses.txt -> N x 3 x 4 (camera-0 frame: x right, y down, z forward)."""
    path = FsPath(path)
    if not path.is_file():
        raise FileNotFoundError(f"KITTI poses file {str(path)!r} does not exist")
    data = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if data.shape[1] != 12 or len(data) < 2:
        raise ValueError(f"{path}: {data.shape} values; expected at least 2 rows of 12 (3 x 4 row-major poses)")
    return data.reshape(-1, 3, 4)


def kitti_path(poses: np.ndarray, *, times: np.ndarray | None = None) -> Path:
    """The ground track of KITTI camera poses in a z-up world: x = cam z, y = -cam x.

    Stationary samples are dropped (arc length must increase); times default to 10 Hz.
    """
    xy = np.stack([poses[:, 2, 3], -poses[:, 0, 3]], axis=1)
    yaw = np.unwrap(np.arctan2(-poses[:, 0, 2], poses[:, 2, 2]))
    t = np.arange(len(poses)) * 0.1 if times is None else np.asarray(times, dtype=np.float64)
    if len(t) != len(poses):
        raise ValueError(f"{len(t)} times for {len(poses)} poses; they must match")
    seg = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 0.02])
    return Path(xy=xy[keep], yaw=yaw[keep], s=s[keep], t=t[keep] - t[0])


def load_kitti_path(poses_file: str | FsPath) -> Path:
    """poses.txt (and times.txt beside it, if present) -> Path."""
    poses = load_kitti_poses(poses_file)
    times_file = FsPath(poses_file).with_name("times.txt")
    times = np.loadtxt(times_file, ndmin=1) if times_file.is_file() else None
    if times is not None and len(times) != len(poses):
        times = None
    return kitti_path(poses, times=times)


def change_lanes(path: Path, *, seed: int, lanes: tuple[float, ...] = (-LANE_WIDTH, 0.0, 0.0, LANE_WIDTH),
                 every: tuple[float, float] = (150.0, 400.0), blend: float = 30.0, drive: int = 0) -> Path:
    """The path moved sideways by a lane offset (metres, + = left) that changes every 150-400 m.

    Changes are smooth (``blend`` metres); headings follow the lateral motion. Revisits of a
    street then often happen in another lane than the first visit. ``drive`` picks the
    random stream (0: a city's first drive).
    """
    rng = rng_for(seed, 5, *drive_keys(drive))
    s = path.s - path.s[0]
    edges, values = [0.0], [float(rng.choice(lanes))]
    while edges[-1] < s[-1]:
        edges.append(edges[-1] + float(rng.uniform(*every)))
        values.append(float(rng.choice(lanes)))
    k = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, len(values) - 1)
    prev = np.asarray(values)[np.maximum(k - 1, 0)]
    cur = np.asarray(values)[k]
    w = _smooth_step((s - np.asarray(edges)[k]) / blend)
    offset = np.where(k == 0, cur, prev + (cur - prev) * w)
    slope = np.gradient(offset, s) if len(s) > 1 else np.zeros_like(s)
    left = np.stack([-np.sin(path.yaw), np.cos(path.yaw)], axis=1)
    return Path(xy=path.xy + offset[:, None] * left, yaw=path.yaw + np.arctan(slope), s=path.s, t=path.t)


def reversed_path(path: Path) -> Path:
    """The same track driven the other way: arc length and time from 0 at the old end, headings turned."""
    return Path(xy=path.xy[::-1].copy(), yaw=path.yaw[::-1] + np.pi, s=path.s[-1] - path.s[::-1],
                t=path.t[-1] - path.t[::-1])


def drive_along(track: Path, *, length: float, seed: int, drive: int, variant: int = 0) -> Path:
    """Drive ``drive`` over a fixed track (the KITTI-00 window a city was built around).

    Drive 0 is the track itself. Drive K > 0 drives it the other way when K is odd, starting
    between 30 % and all of the track's spare length (beyond ``length`` metres) from its
    beginning, drawn from the drive's own stream (``variant`` > 0: another draw).
    """
    if drive == 0:
        return track
    rng = rng_for(seed, 6, *drive_keys(drive, variant=variant))
    path = reversed_path(track) if drive % 2 else track
    slack = max(path.length - length - 1.0, 0.0)
    start = path.s[0] + float(rng.uniform(0.3 * slack, slack))
    first = max(int(np.searchsorted(path.s, start, side="right")) - 1, 0)
    return Path(xy=path.xy[first:], yaw=path.yaw[first:], s=path.s[first:], t=path.t[first:] - path.t[first])


def _track_xy(track: np.ndarray | Path | Keyframes) -> np.ndarray:
    xy = track.xy if isinstance(track, Path | Keyframes) else track
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0:
        raise ValueError(f"positions of shape {xy.shape}; expected N x 2 with N >= 1 (x, y in metres)")
    return xy


def shared_ground(path_a: np.ndarray | Path | Keyframes, path_b: np.ndarray | Path | Keyframes, *,
                  radius: float = 9.0) -> np.ndarray:
    """Which positions of drive B lie within ``radius`` metres of drive A's path: a bool per B position.

    A is the polyline through its positions (a dense path or keyframes, in driving order), so
    B's positions between two of A's keyframes count too. Both must be in one world frame:
    positions of drives through two different cities are not comparable.
    """
    if not radius > 0:
        raise ValueError(f"radius={radius}; it must be positive (metres)")
    a, b = _track_xy(path_a), _track_xy(path_b)
    if len(a) == 1:
        a = np.concatenate([a, a])
    p0, p1 = a[:-1], a[1:]
    lo, hi = np.minimum(p0, p1) - radius, np.maximum(p0, p1) + radius
    out = np.zeros(len(b), dtype=bool)
    for start in range(0, len(b), 256):  # consecutive positions are close: their box prunes most segments
        q = b[start:start + 256]
        near = np.all((hi >= q.min(axis=0)) & (lo <= q.max(axis=0)), axis=1)
        if not near.any():
            continue
        s0, d = p0[near], p1[near] - p0[near]
        rel = q[:, None, :] - s0[None, :, :]
        f = np.clip(np.einsum("qnk,nk->qn", rel, d) / np.maximum(np.einsum("nk,nk->n", d, d), 1e-12), 0.0, 1.0)
        gap = rel - f[:, :, None] * d[None, :, :]
        out[start:start + 256] = (np.einsum("qnk,qnk->qn", gap, gap) <= radius * radius).any(axis=1)
    return out


# ----------------------------------------------------------------------------- keyframes, revisits


def sample_keyframes(path: Path, *, spacing: float, count: int, t0: float = 1.7e9) -> Keyframes:
    """``count`` poses every ``spacing`` metres along the path (fewer if the path is shorter)."""
    if spacing <= 0:
        raise ValueError(f"keyframe spacing {spacing} m; it must be positive")
    n = min(count, int(np.floor(path.length / spacing)) + 1)
    s = path.s[0] + np.arange(n) * spacing
    xy, yaw, t = path.at(s)
    return Keyframes(xy=xy, yaw=yaw, stamps=t0 + t, s=s)


@dataclass(frozen=True)
class RevisitStats:
    """How many frames come back within ``radius`` of a frame at least ``min_gap_s`` older."""

    frames: int
    length_m: float
    duration_s: float
    revisits: int
    same_direction: int
    opposite_direction: int
    radius: float
    min_gap_s: float


def revisit_stats(xy: np.ndarray, yaw: np.ndarray, stamps: np.ndarray, *, radius: float = 9.0,
                  min_gap_s: float = 30.0) -> RevisitStats:
    """Count frames with a true loop: an older frame (more than min_gap_s earlier) within radius metres.

    ``same_direction`` counts frames with such a match heading within 90 degrees of
    theirs, ``opposite_direction`` frames with one heading the other way (a frame can
    count in both).
    """
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    n = len(xy)
    any_ = same = opp = 0
    for lo in range(0, n, 512):
        q = xy[lo:lo + 512]
        d = np.hypot(q[:, None, 0] - xy[None, :, 0], q[:, None, 1] - xy[None, :, 1])
        match = (d <= radius) & (stamps[lo:lo + 512, None] - stamps[None, :] > min_gap_s)
        dyaw = np.abs((yaw[lo:lo + 512, None] - yaw[None, :] + np.pi) % (2 * np.pi) - np.pi)
        any_ += int(match.any(axis=1).sum())
        same += int((match & (dyaw < np.pi / 2)).any(axis=1).sum())
        opp += int((match & (dyaw >= np.pi / 2)).any(axis=1).sum())
    length = float(np.hypot(*np.diff(xy, axis=0).T).sum()) if n > 1 else 0.0
    duration = float(stamps[-1] - stamps[0]) if n > 1 else 0.0
    return RevisitStats(n, length, duration, any_, same, opp, radius, min_gap_s)

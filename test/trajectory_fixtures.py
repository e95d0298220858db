"""Hand-made trajectories for the pose-graph and loop-report tests."""
from __future__ import annotations

import math

import numpy as np


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, *, yaw: float = 0.0, roll: float = 0.0,
         pitch: float = 0.0) -> np.ndarray:
    """world_T_body from a position and ZYX Euler angles in degrees."""
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    out = np.eye(4)
    out[:3, :3] = (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
                   @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))
    out[:3, 3] = (x, y, z)
    return out


def square_laps(*, side: float = 25.0, step: float = 2.0, laps: int = 4) -> tuple[np.ndarray, int]:
    """Counter-clockwise laps of a square from (0, 0) facing +x; (poses (N, 4, 4), poses per lap)."""
    per_lap = int(round(4 * side / step))
    corners = [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)]
    heading = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]
    poses = []
    for i in range(laps * per_lap + 1):
        s = (i * step) % (4 * side)
        k = min(int(s // side), 3)
        u = s - k * side
        (cx, cy), (dx, dy) = corners[k], heading[k]
        poses.append(pose(cx + dx * u, cy + dy * u, yaw=90.0 * k))
    return np.stack(poses), per_lap


def quarter_lap_apart(*, moved: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two runs round one 40 m square in 0.5 m steps: the first from a corner, the second a quarter lap ahead with
    drifting odometry (``DriftModel(seed, 0.2 deg/m)``) kept in an odometry frame moved by ``moved``^-1 (the
    second run's frame in the first's is ``moved``). (first's truth, second's truth, second's odometry), N x 4 x 4."""
    from lcpr_core.posegraph import DriftModel, drift_odometry

    first, per_lap = square_laps(side=40.0, step=0.5, laps=1)
    second = np.roll(first, -per_lap // 4, axis=0)
    drifted, _ = drift_odometry(second, model=DriftModel(seed=seed, yaw_deg_per_m=0.2))
    return first, second, np.linalg.inv(moved) @ drifted

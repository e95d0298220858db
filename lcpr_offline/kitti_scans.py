"""The four raw KITTI-00 scans in ``../shared/data/kitti00``, turned and shifted, as a test of the verifier's starts.

A 360 deg HDL-64 scan, unlike the Livox Avia's 70 deg view, sees the same place whichever way the
car faces: the verifier must then find the relative pose with no odometry and no yaw prior.
:func:`kitti_trials` makes such cases with a known answer: every ordered pair of the scans
000000, 000001, 000005 and 000015 (0.9 to 12 m apart), the query cloud turned about z by a seeded
random yaw in [0, 360) deg and shifted by up to 2 m; the known answer is the scans' relative pose
(poses.txt refined by a dense registration of the raw scans, see :func:`registered_pose`) composed with
that turn and shift. :func:`kitti_start_trials` verifies each with no
initial guess and again from the true relative pose, so that a failure can be told apart: a wrong
start (the truth is accepted) or a pair the fine stage cannot accept at all. Used by
benchmarks/tools/verify_kitti_starts.py, benchmarks/studies/global_registration.py and the tests.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lcpr_common.shared_data import shared_path
from lcpr_core.errors import DatasetFileError, InvalidValueError
from lcpr_core.verification import GeometricVerifier, PreparedCloud
from lcpr_offline.verification_pairs import pose_error

#: The scans in ``kitti00`` (frame numbers of sequence 00).
FRAMES: tuple[int, ...] = (0, 1, 5, 15)
#: A pose counts as right within this translation (m) and rotation (deg) of the truth.
RIGHT_M, RIGHT_DEG = 0.5, 3.0
#: The query is shifted by up to this (m, horizontal) besides its turn.
MAX_SHIFT_M = 2.0
#: Where the known relative pose comes from: "registered" (default) refines poses.txt by a dense registration
#: of the two raw scans; "poses" takes poses.txt as it is.
REFERENCES: tuple[str, ...] = ("registered", "poses")

# camera_T_velodyne ("Tr") of KITTI odometry sequence 00, from the sequence's calib.txt (a published
# constant; the shared folder holds poses.txt but not calib.txt).
CAM_T_VELO = np.array([
    [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
    [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
    [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
    [0.0, 0.0, 0.0, 1.0],
])


def kitti_folder() -> Path:
    """``../shared/data/kitti00`` (or under ``$LCPR_SHARED_DIR``); it may not exist."""
    return shared_path("data", "kitti00")


def load_scan(folder: Path, frame: int) -> np.ndarray:
    """N x 4 float32 (x, y, z, reflectance; x forward) of ``folder/NNNNNN.bin``."""
    path = Path(folder) / f"{frame:06d}.bin"
    if not path.is_file():
        raise DatasetFileError(f"KITTI scan {path} not found; expected the scans {FRAMES} in {folder}")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def lidar_poses(folder: Path, frames: tuple[int, ...] = FRAMES) -> np.ndarray:
    """len(frames) x 4 x 4 world_T_velodyne, the world being the first Velodyne frame.

    poses.txt holds cam0 poses; the Velodyne's is ``Tr^-1 . pose . Tr``.
    """
    path = Path(folder) / "poses.txt"
    if not path.is_file():
        raise DatasetFileError(f"KITTI poses {path} not found; expected sequence 00's poses.txt in {folder}")
    values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if values.shape[1] != 12 or max(frames) >= len(values):
        raise DatasetFileError(f"{path}: {values.shape[0]} poses of {values.shape[1]} numbers; expected 12 numbers "
                               f"a line and frames up to {max(frames)}")
    cam = np.tile(np.eye(4), (len(frames), 1, 1))
    cam[:, :3, :4] = values[list(frames)].reshape(-1, 3, 4)
    velo_T_cam = np.linalg.inv(CAM_T_VELO)
    return np.einsum("ij,njk,kl->nil", velo_T_cam, cam, CAM_T_VELO)


def registered_pose(query_xyz: np.ndarray, match_xyz: np.ndarray, start: np.ndarray) -> np.ndarray:
    """4 x 4 match_T_query of two raw scans by dense GICP (0.2 m voxels) from ``start``.

    Why: at the start of sequence 00 poses.txt moves the car a constant 0.859 m a frame, while
    registering the scans (GICP or point-to-plane, with or without the ground, from poses.txt or from
    identity) agrees within 5 cm on an accelerating car: 0.69 m from frame 0 to 1, 3.58 m (not 4.29) to
    frame 5, 11.7 m (not 12.9) and 1.6 deg to frame 15. A 0.5 m / 3 deg test against poses.txt would
    score the fine stage's agreement with that error, not the verifier.
    """
    import small_gicp

    result = small_gicp.align(np.asarray(match_xyz, np.float64), np.asarray(query_xyz, np.float64),
                              init_T_target_source=start, registration_type="GICP", downsampling_resolution=0.2,
                              max_correspondence_distance=1.0, max_iterations=50, num_threads=1)
    return np.asarray(result.T_target_source, np.float64)


def turn_and_shift(yaw_deg: float, shift_xy: np.ndarray) -> np.ndarray:
    """4 x 4 ``turned_T_original``: a turn of ``yaw_deg`` about z, then a horizontal shift (m)."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    A = np.eye(4)
    A[:2, :2] = [[c, -s], [s, c]]
    A[:2, 3] = shift_xy
    return A


@dataclass(frozen=True)
class KittiTrial:
    """One case with a known answer: ``match_T_query`` maps the turned query cloud into the match's frame."""

    query: int  # frame numbers
    match: int
    distance_m: float  # between the two scans' positions
    yaw_deg: float  # the turn applied to the query
    shift_m: float  # the length of the horizontal shift applied to the query
    query_xyz: np.ndarray  # N x 3 float32, turned and shifted
    match_xyz: np.ndarray  # M x 3 float32, as recorded
    match_T_query: np.ndarray  # 4 x 4 float64, the truth


def reference_poses(*, folder: Path | None = None, reference: str = "registered",
                    frames: tuple[int, ...] = FRAMES) -> dict[tuple[int, int], np.ndarray]:
    """match_T_query (4 x 4) of every ordered pair (query, match) of ``frames``, from ``reference`` (REFERENCES)."""
    if reference not in REFERENCES:
        raise InvalidValueError(f"reference={reference!r}; accepted: {', '.join(REFERENCES)}")
    root = Path(folder) if folder is not None else kitti_folder()
    poses = lidar_poses(root, frames)
    found: dict[tuple[int, int], np.ndarray] = {}
    for (qi, q), (mi, m) in itertools.combinations(enumerate(frames), 2):
        T = np.linalg.inv(poses[mi]) @ poses[qi]
        if reference == "registered":
            T = registered_pose(load_scan(root, q)[:, :3], load_scan(root, m)[:, :3], T)
        found[q, m], found[m, q] = T, np.linalg.inv(T)
    return found


def kitti_trials(*, trials: int, seed: int, folder: Path | None = None, reference: str = "registered",
                 frames: tuple[int, ...] = FRAMES) -> Iterator[KittiTrial]:
    """``trials`` turned-and-shifted queries for every ordered pair of ``frames`` (seeded, reproducible).

    The arguments are checked at the call, the scans read at the first trial.
    """
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise InvalidValueError(f"trials={trials!r}; accepted: an integer >= 1")
    unknown = sorted(set(frames) - set(FRAMES))
    if unknown or len(set(frames)) < 2:
        raise InvalidValueError(f"frames={frames!r}; accepted: two or more of {FRAMES}")
    if reference not in REFERENCES:
        raise InvalidValueError(f"reference={reference!r}; accepted: {', '.join(REFERENCES)}")
    root = Path(folder) if folder is not None else kitti_folder()
    return _trials(trials, seed, root, reference, tuple(dict.fromkeys(frames)))


def _trials(trials: int, seed: int, root: Path, reference: str, frames: tuple[int, ...]) -> Iterator[KittiTrial]:
    known = reference_poses(folder=root, reference=reference, frames=frames)
    scans = {f: load_scan(root, f)[:, :3] for f in frames}
    rng = np.random.default_rng(seed)
    for q, m in itertools.permutations(frames, 2):
        truth = known[q, m]
        for _ in range(trials):
            yaw = float(rng.uniform(0.0, 360.0))
            angle = float(rng.uniform(0.0, 2.0 * math.pi))
            length = float(rng.uniform(0.0, MAX_SHIFT_M))
            A = turn_and_shift(yaw, np.array([math.cos(angle), math.sin(angle)]) * length)
            turned = (scans[q].astype(np.float64) @ A[:3, :3].T + A[:3, 3]).astype(np.float32)
            yield KittiTrial(query=q, match=m, distance_m=float(np.linalg.norm(truth[:3, 3])), yaw_deg=yaw,
                             shift_m=length, query_xyz=turned, match_xyz=scans[m],
                             match_T_query=truth @ np.linalg.inv(A))


def kitti_start_trials(verifier: GeometricVerifier, *, trials: int = 10, seed: int = 0,
                       folder: Path | None = None, reference: str = "registered",
                       frames: tuple[int, ...] = FRAMES) -> list[dict[str, Any]]:
    """Verify every trial of :func:`kitti_trials` with no initial guess and from the truth; one dict per trial.

    Keys: query, match, distance_m, yaw_deg, shift_m; then for ``blind`` (no guess) and ``truth``
    (``initial_guess`` = the true pose), prefixed by that name: accepted, reason, pose_ok (the result,
    accepted or not, within RIGHT_M / RIGHT_DEG of the truth), right (accepted and pose_ok), err_m, err_deg,
    fitness, coarse_fitness, seconds.
    """
    matches: dict[int, PreparedCloud] = {}
    rows: list[dict[str, Any]] = []
    for trial in kitti_trials(trials=trials, seed=seed, folder=folder, reference=reference, frames=frames):
        if trial.match not in matches:
            matches[trial.match] = verifier.prepare(verifier.compact(trial.match_xyz))
        query = verifier.prepare(verifier.compact(trial.query_xyz))
        row: dict[str, Any] = {"query": trial.query, "match": trial.match, "distance_m": trial.distance_m,
                               "yaw_deg": trial.yaw_deg, "shift_m": trial.shift_m}
        for name, guess in (("blind", None), ("truth", trial.match_T_query)):
            v = verifier.verify_prepared(query, matches[trial.match], initial_guess=guess)
            err_m, err_deg = pose_error(v.match_T_query, trial.match_T_query)
            row.update({f"{name}_accepted": v.accepted, f"{name}_reason": v.reason,
                        f"{name}_pose_ok": bool(err_m <= RIGHT_M and err_deg <= RIGHT_DEG),
                        f"{name}_right": bool(v.accepted and err_m <= RIGHT_M and err_deg <= RIGHT_DEG),
                        f"{name}_err_m": err_m, f"{name}_err_deg": err_deg, f"{name}_fitness": v.fitness,
                        f"{name}_coarse_fitness": v.coarse_fitness, f"{name}_seconds": v.seconds})
        rows.append(row)
    return rows

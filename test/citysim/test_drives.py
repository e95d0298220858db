"""Several drives through one synthetic city (``SynthConfig.drive`` / ``citysim --drive``)."""
from __future__ import annotations

import hashlib
from dataclasses import fields, replace

import numpy as np
import pytest

from citysim import (
    SynthConfig,
    SyntheticDrive,
    cli,
    lighting,
    route_keyframes,
    route_path,
    shared_ground,
)
from citysim.hashing import DAY_S
from citysim.route import Keyframes
from msg_tools.frames import SensorFrame


def keyframe_digest(k: Keyframes) -> str:
    return hashlib.sha256(k.xy.tobytes() + k.yaw.tobytes() + k.stamps.tobytes()).hexdigest()[:16]


def frame_digest(f: SensorFrame) -> str:
    h = hashlib.sha256(np.asarray(f.pose, dtype=np.float64).tobytes() + np.float64(f.stamp).tobytes()
                       + f.cloud.tobytes())
    for cam in f.cameras:
        if cam is None:
            h.update(b"none")
            continue
        for part in (cam.jpeg, cam.rgb, cam.depth, cam.labels):
            if part is not None:
                h.update(part if isinstance(part, bytes) else np.ascontiguousarray(part).tobytes())
    return h.hexdigest()[:16]


@pytest.fixture(scope="module")
def first() -> SyntheticDrive:
    return SyntheticDrive(SynthConfig(rig="kitti", frames=40, keyframe_spacing=5.0, seed=2, image_size=(64, 24)))


@pytest.fixture(scope="module")
def second(first: SyntheticDrive) -> SyntheticDrive:
    return first.other_drive(1)


# ------------------------------------------------------------------------------------------ drive 0 as before

# Made by the code before drives existed (a city had one drive): keyframe poses and stamps of 300-frame
# drives, and one small rendered frame of each rig. Drive 0 must keep giving exactly these bytes.
KEYFRAMES_BEFORE = {
    ("nuscenes", 0, "grid"): "d0a9009b44177936",
    ("nuscenes", 3, "grid"): "d8d778f2f7876950",
    ("kitti", 1, "grid"): "e38b03ff6f23a64a",
}
RENDERS_BEFORE = {"kitti": ("64x24", "a4c826f655574776"), "nuscenes": ("48x27", "5345376d8178b1cc")}


@pytest.mark.parametrize("rig, seed, route", sorted(KEYFRAMES_BEFORE))
@pytest.mark.parametrize("drive", [None, 0])
def test_drive_0_has_the_keyframes_a_seed_had_before_drives_existed(rig: str, seed: int, route: str,
                                                                      drive: int | None) -> None:
    config = SynthConfig(rig=rig, frames=300, seed=seed, route=route)
    if drive is not None:
        config = SynthConfig(rig=rig, frames=300, seed=seed, route=route, drive=drive)
    assert keyframe_digest(route_keyframes(config)) == KEYFRAMES_BEFORE[rig, seed, route]


def test_drive_0_along_kitti00_has_the_keyframes_it_had_before(shared) -> None:
    poses = str(shared / "data" / "kitti00" / "poses.txt")
    config = SynthConfig(rig="kitti", frames=300, seed=0, route="kitti00", kitti_poses=poses, drive=0)
    assert keyframe_digest(route_keyframes(config)) == "dd21d3ee8321b9af"


@pytest.mark.parametrize("rig", sorted(RENDERS_BEFORE))
def test_drive_0_renders_the_bytes_a_seed_rendered_before_drives_existed(rig: str) -> None:
    size, digest = RENDERS_BEFORE[rig]
    w, h = (int(v) for v in size.split("x"))
    drive = SyntheticDrive(SynthConfig(rig=rig, frames=4, seed=2, image_size=(w, h), drive=0))
    assert frame_digest(drive.frame(2)) == digest  # noise, lighting, parked cars, JPEG: all as before


# ------------------------------------------------------------------------------------------ drive K > 0


def test_a_later_drive_keeps_the_city_and_takes_another_route_a_day_later(first: SyntheticDrive,
                                                                         second: SyntheticDrive) -> None:
    rebuilt = SyntheticDrive(replace(first.config, drive=1))  # built from scratch: the same city, the same route
    for f in fields(first.world.objects):
        np.testing.assert_array_equal(getattr(rebuilt.world.objects, f.name), getattr(first.world.objects, f.name))
    np.testing.assert_array_equal(rebuilt.world.ground.codes, first.world.ground.codes)
    np.testing.assert_array_equal(rebuilt.world.slots.x, first.world.slots.x)
    np.testing.assert_array_equal(rebuilt.keyframes.xy, second.keyframes.xy)
    a, b = first.keyframes, second.keyframes
    assert np.hypot(*(a.xy[0] - b.xy[0])) > 20.0  # another start
    assert b.stamps[0] == a.stamps[0] + DAY_S and b.stamps[0] == second.config.t0
    assert not np.isin(b.stamps, a.stamps).any()


def test_a_later_drive_has_its_own_sensor_noise_and_lighting(first: SyntheticDrive) -> None:
    same_route = SyntheticDrive(replace(first.config, drive=3), world=first.world, path=first.path)
    a, b = first.frame(0), same_route.frame(0)
    np.testing.assert_array_equal(a.pose, b.pose)
    assert a.cloud.tobytes() != b.cloud.tobytes()  # same place and city, other noise (and parked cars)
    assert lighting(seed=2, session=0, night=False, drive=1) != lighting(seed=2, session=0, night=False)


def test_a_later_drive_keeps_clear_of_walls_poles_and_parked_cars(second: SyntheticDrive) -> None:
    driven = second.path.xy[second.path.s <= second.keyframes.s[-1]]
    assert second.world.clearance(driven).min() >= 1.2
    assert second.empty_slots is not None
    parked_on_route = second.world.slots_near(driven, radius=1.5) & ~second.empty_slots
    assert not parked_on_route.any()


@pytest.mark.parametrize("rig, seed, least", [("nuscenes", 0, 0.55), ("nuscenes", 3, 0.7), ("nuscenes", 7, 0.6),
                                              ("kitti", 1, 0.55)])
def test_drives_0_and_1_of_a_city_share_much_of_their_streets(rig: str, seed: int, least: float) -> None:
    config = SynthConfig(rig=rig, frames=300, seed=seed)
    path, keys = route_path(config), route_keyframes(config)
    driven = path.xy[path.s <= keys.s[-1]]
    share = shared_ground(driven, route_keyframes(replace(config, drive=1)), radius=9.0).mean()
    assert share >= least


def test_drives_through_different_cities_are_not_compared(first: SyntheticDrive, second: SyntheticDrive) -> None:
    assert first.shared_ground(second).mean() > 0.2
    other_city = SyntheticDrive(replace(first.config, seed=5))
    with pytest.raises(ValueError, match="different cities"):
        first.shared_ground(other_city)
    with pytest.raises(ValueError, match="changes the city"):
        first.other_drive(2, frames=80)


def test_kitti00_drives_share_the_track_and_odd_ones_drive_it_the_other_way(shared) -> None:
    poses = str(shared / "data" / "kitti00" / "poses.txt")
    config = SynthConfig(rig="kitti", frames=300, seed=0, route="kitti00", kitti_poses=poses)
    track = route_path(config)
    k0 = route_keyframes(config)
    for drive in (1, 2):
        k = route_keyframes(replace(config, drive=drive))
        assert len(k) == 300 and shared_ground(track.xy[track.s <= k0.s[-1] + 150.0], k).mean() > 0.9
        i = int(np.argmin(np.hypot(*(k0.xy - k.xy[150]).T)))
        turned = abs((k.yaw[150] - k0.yaw[i] + np.pi) % (2 * np.pi) - np.pi) > np.pi / 2
        assert turned == (drive % 2 == 1)


# ------------------------------------------------------------------------------------------ shared ground, options


def test_shared_ground_counts_positions_near_the_path_also_between_its_points() -> None:
    a = np.array([[0.0, 0.0], [100.0, 0.0]])
    b = np.array([[50.0, 5.0], [50.0, 20.0], [150.0, 0.0], [-5.0, 0.0]])
    np.testing.assert_array_equal(shared_ground(a, b, radius=9.0), [True, False, False, True])
    np.testing.assert_array_equal(shared_ground(a[:1], b, radius=9.0), [False, False, False, True])
    with pytest.raises(ValueError, match="radius=0"):
        shared_ground(a, b, radius=0)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        shared_ground(a, np.zeros(3))


def test_a_negative_drive_or_a_drive_change_of_a_route_is_refused(first: SyntheticDrive) -> None:
    with pytest.raises(ValueError, match="drive=-1"):
        SynthConfig(drive=-1)
    with pytest.raises(ValueError, match="other_drive"):
        first.with_config(drive=2)


def test_the_cli_takes_a_drive_number(tmp_path, capsys) -> None:
    args = cli.build_parser().parse_args(["--drive", "3", "--seed", "4", "--out", str(tmp_path / "x.bag")])
    assert cli.config_from_args(args).drive == 3
    assert cli.main(["--drive", "-2", "--out", str(tmp_path / "x.bag")]) == 2
    assert "drive=-2" in capsys.readouterr().err

"""The synthetic city: determinism, geometry, camera/LiDAR consistency, revisits, bags and the CLI."""
from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from PIL import Image

from citysim import (
    Label,
    LidarNoise,
    SynthConfig,
    SyntheticDrive,
    World,
    cli,
    make_rig,
    write_bag,
)
from citysim import ground as g
from citysim.camera import lighting, render_camera
from citysim.labels import Mat
from citysim.lidar import render_lidar
from citysim.rigs import pose_matrix
from citysim.route import (
    change_lanes,
    grid_path,
    load_kitti_path,
    make_street_graph,
    plan_grid_nodes,
    revisit_stats,
    sample_keyframes,
)
from citysim.world import GroundMap, ObjectsBuilder, ParkingSlots
from lcpr_core import range_image
from msg_tools import KITTI_TOPICS, NUSCENES_TOPICS, read_camera_models, read_frames

EXACT: dict[str, Any] = dict(lidar_noise=LidarNoise.off(), pixel_noise=False, camera_drop=0.0, depth_range=0.0,
                             depth_noise=0.0)


@pytest.fixture(scope="module")
def nus() -> SyntheticDrive:
    return SyntheticDrive(SynthConfig(frames=6, seed=3, image_size=(200, 112)))


@pytest.fixture(scope="module")
def kitti() -> SyntheticDrive:
    return SyntheticDrive(SynthConfig(rig="kitti", frames=30, seed=1, image_size=(620, 188), **EXACT))


def wall_world(*, x: float, y: float, yaw: float, half_depth: float = 0.5, half_width: float = 10.0,
               height: float = 8.0) -> World:
    """One building wall (a box) on an endless road."""
    b = ObjectsBuilder()
    b.box(x, y, half_depth, half_width, yaw, 0.0, height, label=int(Label.BUILDING), mat=Mat.WALL,
          color=(0.5, 0.5, 0.5))
    empty = np.zeros(0)
    return World(objects=b.build(), ground=GroundMap.uniform(g.ROAD), slots=ParkingSlots(empty, empty, empty),
                 lamps=np.zeros((0, 3)), seed=0)


def scan(world: World, rig_name: str, pose: np.ndarray, yaw: float) -> np.ndarray:
    rig = make_rig(rig_name)
    objects = world.objects_near(pose[0, 3], pose[1, 3], 150.0, stamp=0.0)
    return render_lidar(objects, world.ground, rig.lidar, pose @ rig.lidar.base_T_lidar, yaw, np.random.default_rng(0),
                        noise=LidarNoise.off())


# ------------------------------------------------------------------------------------------ determinism


def test_the_same_seed_gives_identical_frames_and_bytes(nus: SyntheticDrive) -> None:
    again = SyntheticDrive(nus.config)
    for i in (0, 4):
        a, b = nus.frame(i), again.frame(i)
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.pose, b.pose)
        assert a.cloud.tobytes() == b.cloud.tobytes()
        assert [c.jpeg if c else None for c in a.cameras] == [c.jpeg if c else None for c in b.cameras]


def test_worker_processes_give_the_same_frames_as_one_process(nus: SyntheticDrive) -> None:
    serial = list(nus.frames(start=1, stop=4))
    parallel = list(nus.frames(workers=2, start=1, stop=4))
    assert [f.extras["index"] for f in parallel] == [1, 2, 3]
    for a, b in zip(serial, parallel, strict=True):
        assert a.cloud.tobytes() == b.cloud.tobytes()
        assert [c.jpeg if c else None for c in a.cameras] == [c.jpeg if c else None for c in b.cameras]


def test_another_seed_gives_another_city(nus: SyntheticDrive) -> None:
    other = SyntheticDrive(SynthConfig(frames=6, seed=4, image_size=(200, 112)))
    assert len(other.world.objects) != len(nus.world.objects) or not np.array_equal(other.world.objects.cx,
                                                                                     nus.world.objects.cx)


# ------------------------------------------------------------------------------------------ geometry


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_nuscenes_lidar_sees_a_known_wall_and_flat_ground(yaw: float) -> None:
    # a wall 20 m ahead of base_link (front face at 19.5 m), LIDAR_TOP 0.94 m ahead, 1.84 m up, x right, y forward
    c, s = np.cos(yaw), np.sin(yaw)
    pose = pose_matrix(3.0, -7.0, 0.0, yaw)
    world = wall_world(x=3.0 + 20.0 * c, y=-7.0 + 20.0 * s, yaw=yaw)
    cloud = scan(world, "nuscenes", pose, yaw)
    wall = cloud[cloud["label"] == Label.BUILDING]
    ground = cloud[cloud["label"] == Label.ROAD]
    assert len(wall) > 1000 and len(ground) > 10000
    np.testing.assert_allclose(wall["y"], 19.5 - 0.94, atol=1e-3)  # forward distance to the wall face
    assert np.abs(wall["x"]).max() <= 10.0 + 1e-3  # the wall is 20 m wide
    assert wall["z"].max() <= 8.0 - 1.84 + 1e-3
    np.testing.assert_allclose(ground["z"], -1.84, atol=1e-3)
    r = np.sqrt(ground["x"] ** 2 + ground["y"] ** 2 + ground["z"] ** 2)
    elev = np.degrees(np.arcsin(ground["z"] / r))
    beams = 10.0 - (np.arange(32) + 0.5) * 40.0 / 32
    np.testing.assert_allclose(elev, beams[31 - ground["ring"].astype(int)], atol=1e-3)  # ring 0 = lowest beam


def test_lcpr_range_image_takes_the_nuscenes_cloud_unchanged() -> None:
    world = wall_world(x=0.0, y=30.0, yaw=np.pi / 2, half_width=40.0, height=30.0)  # a wall on the left
    cloud = scan(world, "nuscenes", pose_matrix(0.0, 0.0, 0.0, 0.0), 0.0)
    pts = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    image = range_image(pts)
    assert image.shape == (32, 1056)
    assert ((image > 0).sum(axis=1) > 300).all()  # every beam lands in its own row
    wall = range_image(pts[cloud["label"] == Label.BUILDING])
    assert wall[wall > 0].min() == pytest.approx(29.5, abs=0.01)  # perpendicular distance to the wall face
    u = np.nonzero((wall > 0).any(axis=0))[0]
    assert u.max() < 1056 // 2  # the wall is on the left: the left half of the range image


def test_kitti_lidar_is_in_the_velodyne_frame() -> None:
    world = wall_world(x=15.0, y=0.0, yaw=0.0)
    cloud = scan(world, "kitti", pose_matrix(0.0, 0.0, 1.73, 0.0), 0.0)
    wall = cloud[cloud["label"] == Label.BUILDING]
    np.testing.assert_allclose(wall["x"], 14.5, atol=1e-3)  # x forward
    np.testing.assert_allclose(cloud[cloud["label"] == Label.ROAD]["z"], -1.73, atol=1e-3)
    assert 0.0 <= cloud["intensity"].min() and cloud["intensity"].max() <= 1.0
    assert set(np.unique(cloud["ring"])) == set(range(64))


def test_camera_depth_and_labels_match_the_geometry() -> None:
    world = wall_world(x=20.0, y=0.0, yaw=0.0, height=4.0)
    rig = make_rig("kitti", image_size=(400, 121))
    cam = rig.cameras[0]
    pose = pose_matrix(0.0, 0.0, 1.73, 0.0)
    objects = world.objects_near(0.0, 0.0, 150.0, stamp=0.0)
    r = render_camera(objects, world.ground, cam, pose @ cam.base_T_cam, lighting(seed=0, session=0, night=False),
                      np.random.default_rng(0), vehicle_yaw=0.0, noise=False)
    fx, cy = cam.K[0, 0], cam.K[1, 2]
    wall = r.labels == Label.BUILDING
    np.testing.assert_allclose(r.depth[wall], 19.5 - 0.27, atol=1e-3)  # optical-axis depth to the face
    v = int(np.ceil(cy)) + 20  # a row below the horizon and below the wall's foot: the road
    assert r.labels[v, 5] == Label.ROAD
    assert r.depth[v, 5] == pytest.approx(fx * 1.65 / (v - cy), rel=1e-4)  # camera 1.65 m above the ground
    assert (r.depth[r.labels == 0] == 0).all() and (r.labels[0] == 0).all()  # sky at the top: no depth, label 0


def test_camera_labels_and_depth_agree_with_the_lidar(kitti: SyntheticDrive) -> None:
    cam = kitti.rig.cameras[0]
    cam_T_base = np.linalg.inv(cam.base_T_cam)
    for i in (3, 17):
        frame = kitti.frame(i)
        image = frame.cameras[0]
        assert image is not None and image.labels is not None and image.depth is not None
        p = frame.xyz @ cam_T_base[:3, :3].T + cam_T_base[:3, 3]  # base_link = velodyne for the KITTI rig
        front = p[:, 2] > 1.0
        uvw = p[front] @ cam.K.T
        u = np.floor(uvw[:, 0] / uvw[:, 2] + 0.5).astype(int)
        v = np.floor(uvw[:, 1] / uvw[:, 2] + 0.5).astype(int)
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        assert inside.sum() > 5000
        lidar_labels = frame.cloud["label"][front][inside] & 0xFFFF
        same = lidar_labels == image.labels[v[inside], u[inside]]
        assert same.mean() > 0.9
        depth_err = np.abs(image.depth[v[inside], u[inside]][same] - p[front][inside][same, 2])
        assert np.median(depth_err) < 0.1


# ------------------------------------------------------------------------------------------ drives and realism


def test_grid_drives_revisit_places_in_both_directions_and_other_lanes() -> None:
    graph = make_street_graph(seed=5, inner=(2, 2))
    path = grid_path(graph, plan_grid_nodes(graph, length_m=1500.0, seed=5), seed=5)
    kf = sample_keyframes(path, spacing=5.0, count=300)
    stats = revisit_stats(kf.xy, kf.yaw, kf.stamps)
    assert stats.revisits > 30 and stats.same_direction > 0 and stats.opposite_direction > 0
    # revisits are not all on the same line: lane changes / other direction shift them sideways
    d = np.hypot(*(kf.xy[:, None, :] - kf.xy[None, :, :]).transpose(2, 0, 1))
    old = kf.stamps[:, None] - kf.stamps[None, :] > 30.0
    nearest = np.where(old, d, np.inf).min(axis=1)
    revisit = nearest <= 9.0
    assert (nearest[revisit] > 2.0).sum() > 5


def test_parked_cars_change_between_visits(nus: SyntheticDrive) -> None:
    x, y = nus.keyframes.xy[0]

    def cars(stamp: float) -> set[tuple[float, float, int]]:
        o = nus.world.objects_near(x, y, 100.0, stamp=stamp)
        sel = (o.label & 0xFFFF) == Label.CAR
        return set(zip(np.round(o.cx[sel], 2), np.round(o.cy[sel], 2), o.label[sel].tolist(), strict=True))

    now, later = cars(0.0), cars(900.0)
    assert now and later and now != later
    assert now & later  # some cars stay parked for the whole drive
    assert cars(0.0) == now  # a visit's layout is reproducible


def test_night_is_darker_and_cameras_can_drop(nus: SyntheticDrive) -> None:
    day = nus.with_config(night_fraction=0.0).frame(2)
    night = nus.with_config(night_fraction=1.0, camera_drop=0.5).frame(2)
    assert night.extras["night"] and not day.extras["night"]
    mean = lambda img: np.asarray(Image.open(io.BytesIO(img.jpeg))).mean()  # noqa: E731
    pairs = [(d, n) for d, n in zip(day.cameras, night.cameras, strict=True) if d is not None and n is not None]
    assert pairs and all(mean(n) < 0.7 * mean(d) for d, n in pairs)
    assert any(c is None for c in night.cameras) or all(c is None for c in day.cameras)


def test_lidar_noise_and_dropouts_change_the_scan(nus: SyntheticDrive) -> None:
    noisy = nus.frame(1).cloud
    exact = nus.with_config(**EXACT).frame(1).cloud
    assert 0.8 * len(exact) < len(noisy) < 0.99 * len(exact)
    ground = exact[(exact["label"] == Label.ROAD) & (np.hypot(exact["x"], exact["y"]) < 15)]
    np.testing.assert_allclose(ground["z"], -1.84, atol=1e-3)


def test_kitti00_route_follows_the_real_trajectory_with_roads_under_it(shared) -> None:
    poses = shared / "data" / "kitti00" / "poses.txt"
    config = SynthConfig(rig="kitti", route="kitti00", kitti_poses=str(poses), frames=40, keyframe_spacing=5.0,
                         image_size=(200, 61), lane_changes=False, **EXACT)
    drive = SyntheticDrive(config)
    path = load_kitti_path(poses)
    kf = drive.keyframes
    assert len(kf) == 40 and kf.xy[0] == pytest.approx(path.xy[0])
    assert np.allclose(kf.s, np.arange(40) * 5.0)
    xy, _, _ = path.at(kf.s)
    np.testing.assert_allclose(kf.xy, xy)  # the real KITTI-00 ground track (x = cam z, y = -cam x)
    road = (g.ROAD, g.MARK_WHITE, g.ROAD_EDGE)
    assert np.isin(drive.world.ground.lookup(kf.xy[:, 0], kf.xy[:, 1]), road).all()
    frame = drive.frame(10)
    labels = frame.cloud["label"] & 0xFFFF
    assert (labels == Label.BUILDING).sum() > 100 and (labels == Label.SIDEWALK).sum() > 100
    # lane changes: the drive moves a lane (3.5 m) sideways now and then, and stays on the road
    side = np.hypot(*(change_lanes(path, seed=0).xy - path.xy).T)
    assert side.max() == pytest.approx(3.5, abs=0.01) and side.min() < 0.01 and 0.2 < (side > 1.0).mean() < 0.8
    moved = SyntheticDrive(replace(config, lane_changes=True, frames=120))
    assert np.isin(moved.world.ground.lookup(*moved.keyframes.xy.T), road).all()


# ------------------------------------------------------------------------------------------ bags and CLI


def read_all(path, topics) -> list:
    return list(read_frames(path, topics=topics))


def test_nuscenes_bag_round_trip(nus: SyntheticDrive, tmp_path) -> None:
    report = write_bag(nus, tmp_path / "nus.bag")
    assert report.frames == len(nus) == 6
    back = read_all(tmp_path / "nus.bag", NUSCENES_TOPICS)
    assert len(back) == 6
    for i, f in enumerate(back):
        ref = nus.frame(i)
        assert f.stamp == pytest.approx(ref.stamp, abs=1e-6)
        assert f.pose is not None and ref.pose is not None
        np.testing.assert_allclose(f.pose, ref.pose, atol=1e-6)
        assert f.lidar_frame_id == "LIDAR_TOP"
        for name in ("x", "y", "z", "intensity", "ring", "label"):
            np.testing.assert_array_equal(f.cloud[name], ref.cloud[name])
        assert [c.jpeg if c else None for c in f.cameras] == [c.jpeg if c else None for c in ref.cameras]
    models = read_camera_models(tmp_path / "nus.bag", topics=NUSCENES_TOPICS)
    for got, want in zip(models, nus.rig.cameras, strict=True):
        assert got is not None and got.frame_id == want.frame_id
        np.testing.assert_allclose(got.base_T_cam, want.base_T_cam, atol=1e-9)
        np.testing.assert_allclose(got.K, want.K)


def test_kitti_bag_round_trip_keeps_depth_and_labels(kitti: SyntheticDrive, tmp_path) -> None:
    small = SyntheticDrive(SynthConfig(rig="kitti", frames=3, seed=1, image_size=(160, 49), **EXACT),
                           world=kitti.world, path=kitti.path)
    write_bag(small, tmp_path / "kitti.bag")
    back = read_all(tmp_path / "kitti.bag", KITTI_TOPICS)
    assert len(back) == 3
    ref = small.frame(2)
    got = back[2].cameras[0]
    assert got is not None and ref.cameras[0] is not None
    np.testing.assert_array_equal(got.rgb, ref.cameras[0].rgb)
    np.testing.assert_array_equal(got.depth, ref.cameras[0].depth)
    np.testing.assert_array_equal(got.labels, ref.cameras[0].labels)
    assert back[2].lidar_frame_id == "velodyne"


def test_cli_writes_a_bag_and_reports_revisits(tmp_path, capsys) -> None:
    out = tmp_path / "cli.bag"
    rc = cli.main(["--frames", "3", "--image-size", "96x54", "--workers", "1", "--no-progress", "--seed", "2",
                   "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "frames:     3" in text and "revisits:" in text and "driven:" in text
    assert len(read_all(out, NUSCENES_TOPICS)) == 3


@pytest.mark.parametrize("make, message", [
    (lambda: SynthConfig(rig="velodyne"), "accepted: nuscenes, kitti"),
    (lambda: SynthConfig(route="mars"), "accepted: grid, kitti00"),
    (lambda: SynthConfig(night_fraction=1.5), "night_fraction=1.5"),
    (lambda: SynthConfig(frames=0), "frames=0"),
    (lambda: make_rig("kitti", image_size=(8, 8)), "8x8"),
])
def test_bad_options_name_the_value_and_what_is_accepted(make: Callable[[], object], message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(".", r"\.")):
        make()


def test_cli_reports_bad_values(tmp_path, capsys) -> None:
    assert cli.main(["--night-fraction", "2", "--out", str(tmp_path / "x.bag")]) == 2
    assert "night_fraction=2.0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["--image-size", "big", "--out", str(tmp_path / "x.bag")])

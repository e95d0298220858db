"""A synthetic city with revisiting drives, rendered for a nuScenes-like or a KITTI-like rig.

    from citysim import SynthConfig, SyntheticDrive, write_bag
    drive = SyntheticDrive(SynthConfig(rig="nuscenes", frames=300, seed=0))
    for frame in drive.frames(workers=2):   # msg_tools.frames.SensorFrame, in order
        ...
    write_bag(drive, "out/synth.bag")       # or the console script citysim
    second = drive.other_drive(1)           # another route through the same city, a day later
    drive.shared_ground(second).mean()      # share of its keyframes on drive 0's streets

Modules: world (the city model), citygen/props/ground (seeded generation), route (street
graph, drives, KITTI-00 import), raycast (2.5-D ray casting), camera, lidar, materials,
rigs, drive (the frame generator), bagout (rosbag2 writing), cli.
"""
from .bagout import WriteReport, write_bag, write_bag_once
from .camera import Lighting, lighting
from .citygen import CityConfig, grid_city, path_city
from .drive import SynthConfig, SyntheticDrive, build_city_and_route, generate, route_keyframes, route_path
from .labels import Label, Mat
from .lidar import CLOUD_DTYPE, LidarNoise
from .rigs import LidarModel, Rig, kitti_rig, make_rig, nuscenes_rig
from .route import Keyframes, Path, RevisitStats, StreetGraph, revisit_stats, shared_ground
from .world import GroundMap, Objects, World

__all__ = [
    "CLOUD_DTYPE", "CityConfig", "GroundMap", "Keyframes", "Label", "LidarModel", "LidarNoise", "Lighting", "Mat",
    "Objects", "Path", "RevisitStats", "Rig", "StreetGraph", "SynthConfig", "SyntheticDrive", "World", "WriteReport",
    "build_city_and_route", "generate", "grid_city", "kitti_rig", "lighting", "make_rig", "nuscenes_rig", "path_city",
    "revisit_stats", "route_keyframes", "route_path", "shared_ground", "write_bag", "write_bag_once",
]

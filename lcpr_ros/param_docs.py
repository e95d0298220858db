"""Descriptions, ranges and accepted values of the node's parameters.

Defaults are NOT here: they come from the config dataclasses. A field without an
entry still becomes a parameter (described by its dataclass and field name), so
fields added to the core show up without touching this table.
"""
from __future__ import annotations

import math

from lcpr_core.descriptor_map import INDEX_TYPES
from lcpr_core.lcpr.describer import PRECISIONS, RUNTIMES
from lcpr_core.lcpr.detector import MATCH_METHODS
from lcpr_core.lcpr.preprocess import CUSTOM, PRESETS
from lcpr_core.lcpr.preprocess.cameras import DECODERS
from lcpr_core.verification.submap import SUBMAP_MODES
from ros_common.config import SHARED_DOCS
from ros_common.params import ParamDoc

from .config import CAMERA_TYPES

INF = math.inf
BIG = 2**31 - 1


DOCS: dict[str, ParamDoc] = {
    **SHARED_DOCS,
    # ---- verification (geometric check of every candidate against the LiDAR)
    "verify.enabled": ParamDoc("register each candidate's cloud against the query's and publish verified loops "
                               "only; false = publish the nearest descriptor unchecked (the old behaviour)",
                               dynamic=True),
    "verify.min_fitness": ParamDoc("overlap (0..1) a registration needs to be accepted", 0.0, 1.0, dynamic=True),
    "verify.min_constraint": ParamDoc("smallest per-inlier Hessian eigenvalue (rejects planes, corridors, "
                                      "sphere shells)", 0.0, INF, dynamic=True),
    "verify.registration": ParamDoc("small_gicp registration", choices=("GICP", "PLANE_ICP", "VGICP"),
                                    dynamic=True),
    "verify.num_threads": ParamDoc("registration threads", 1, 64, dynamic=True),
    "verify.max_contradiction": ParamDoc("share (0..1) of either cloud's points that may lie where the other "
                                         "sensor's beams passed through (its free space) before the pair is refused "
                                         "as contradicted, a look-alike place; 1 = no free-space test",
                                         0.0, 1.0, dynamic=True),
    "verify.ambiguity_constraint": ParamDoc("translation constraint (0..1/3) under which a pair about to be "
                                            "accepted is also registered from its other starts (0 = never)",
                                            0.0, 1.0, dynamic=True),
    "verify.ambiguity_ratio": ParamDoc("another pose reaching this share of the accepted fitness refuses the pair "
                                       "as ambiguous", 0.01, 1.0, dynamic=True),
    "verify.ambiguity_distance": ParamDoc("m: how far another pose must lie from the accepted one to count as an "
                                          "alternative", 0.1, 1000.0, dynamic=True),
    "verify.processes": ParamDoc("worker processes verifying a keyframe's candidates side by side (each keeps "
                                 "its own prepared clouds); 0 = in the node's process", 0, 64, dynamic=True),
    "verify.cloud.voxel": ParamDoc("m, voxel size of the compact keyframe cloud kept in the map", 0.05, 5.0),
    "verify.cloud.max_points": ParamDoc("points kept per keyframe cloud (6 bytes each)", 100, 1_000_000),
    # ---- local submaps (lcpr_core.verification.submap): neighbours stitched by the odometry before verifying
    "submap.mode": ParamDoc("verify local submaps instead of single scans: the query with its previous keyframes, "
                            "each match with its neighbours, stitched by the odometry; auto = on for a keyframe "
                            "whose cloud covers less than submap.auto_fov_deg of azimuth (a narrow field of view "
                            "such as a Livox Avia's), off for 360 deg scans", choices=SUBMAP_MODES, dynamic=True),
    "submap.travel_m": ParamDoc("m of odometry path a neighbour may be from the centre keyframe, on each side",
                                0.01, 1000.0, dynamic=True),
    "submap.max_keyframes": ParamDoc("keyframes stitched into one submap at most, the centre included (nearest "
                                     "by path first)", 1, 1000, dynamic=True),
    "submap.max_gap_s": ParamDoc("s between consecutive keyframes beyond which they are not stitched (another "
                                 "run)", 0.001, 1e6, dynamic=True),
    "submap.voxel": ParamDoc("m, voxel grid of the stitched cloud", 0.05, 5.0, dynamic=True),
    "submap.max_points": ParamDoc("points of a stitched cloud at most (registration time grows with them)",
                                  100, 1_000_000, dynamic=True),
    "submap.auto_fov_deg": ParamDoc("deg of azimuth under which submap.mode auto counts a keyframe's field of "
                                    "view as narrow", 0.0, 360.0, dynamic=True),
    "submap.lidar_xyz": ParamDoc("m: the LiDAR (the clouds' frame) in the odometry's child frame "
                                 "(base_T_lidar), to place neighbours' clouds", dynamic=True),
    "submap.lidar_rpy": ParamDoc("rad: roll, pitch, yaw of the LiDAR in the odometry's child frame (R = Rz Ry Rx)",
                                 dynamic=True),

    # ---- each keyframe's up from its walls (lcpr_core.up), published on ~/up for lcpr_backend
    "up.enabled": ParamDoc("measure each keyframe's up direction from the walls its cloud sees and publish it on "
                           "~/up (lcpr_backend holds the map's roll and pitch with it)", dynamic=True),
    "up.voxel": ParamDoc("m, voxel grid of the cloud before its normals are estimated; 0 = none", 0.0, 5.0,
                         dynamic=True),
    "up.neighbours": ParamDoc("points per normal", 3, 200, dynamic=True),
    "up.planarity": ParamDoc("a point lies on a plane when its smallest covariance eigenvalue is under this share "
                             "of the middle one", 0.0, 1.0, dynamic=True),
    "up.min_range": ParamDoc("m, closer points (the vehicle, the person carrying the sensor) are ignored", 0.0, 1000.0,
                             dynamic=True),
    "up.max_range": ParamDoc("m, farther points are ignored", 0.0, 1000.0, dynamic=True),
    "up.max_tilt_deg": ParamDoc("deg: a plane whose normal is within this of the LiDAR's horizontal plane counts as "
                                "a wall", 0.0, 90.0, dynamic=True),
    "up.inlier_deg": ParamDoc("deg: walls further from vertical than this (roofs, slopes) are dropped while the "
                              "up is refined", 0.0, 90.0, dynamic=True),
    "up.iterations": ParamDoc("refinement passes", 1, 100, dynamic=True),
    "up.min_walls": ParamDoc("wall points needed for an up (fewer: none published)", 1, 1_000_000, dynamic=True),
    "up.min_spread": ParamDoc("the second wall direction's share of the first (eigenvalue ratio) needed; walls "
                              "facing one way leave a tilt unseen", 0.0, 1.0, dynamic=True),
    "up.min_fov_deg": ParamDoc("deg of azimuth a keyframe's cloud must cover for an up (a narrow field of view sees "
                               "the walls of one side only); 0 = any", 0.0, 360.0, dynamic=True),

    # ---- model (read-only: the network is built once)
    "model.weights": ParamDoc("LCPR weights: bundled (the trained weights shipped, synthetic cities), a checkpoint "
                              "file (the authors' released one for a real vehicle), or seeded (random, testing only)"),
    "model.imagenet": ParamDoc("torchvision resnet18 state dict for the ResNet blocks, used when model.weights "
                               "is empty"),
    "model.seed": ParamDoc("seed of the random initialisation, used when both weight files are empty", 0, BIG),
    "model.num_cameras": ParamDoc("cameras in the panorama; must equal the number of camera_topics", 1, 64),
    "model.image_size": ParamDoc("[height, width] each camera image is resized to; multiples of 32 "
                                 "(released: 256, 704)"),
    "model.lidar": ParamDoc("range-image preset of the LiDAR, or custom (model.lidar_geometry.*, rows and "
                            "columns from model.range_size)", choices=(*sorted(PRESETS), CUSTOM)),
    "model.lidar_geometry.fov_up_deg": ParamDoc("deg, top of the vertical field of view (model.lidar custom)"),
    "model.lidar_geometry.fov_down_deg": ParamDoc("deg, bottom of the vertical field of view (model.lidar custom)"),
    "model.lidar_geometry.yaw_offset_deg": ParamDoc("deg about z that turns the cloud's x forward "
                                                    "(model.lidar custom)"),
    "model.lidar_geometry.max_range": ParamDoc("m, farther points are left out (model.lidar custom)"),
    "model.lidar_geometry.min_xy": ParamDoc("m, half size of the ego box left out (model.lidar custom)"),
    "model.range_size": ParamDoc("[height, width] of the range image, multiples of 8; [0, 0] = the preset's"),
    "model.width": ParamDoc("channel multiplier of the network (1.0 = released; must match the weights)", 0.0, 4.0),
    "model.precision": ParamDoc("inference path: auto (CPU: the fastest exact one, measured at start; GPU: the "
                                "fastest of fp32 / tf32 / bf16 within cosine 0.9999 of exact fp32), fp32 (on a GPU "
                                "with TF32 off: the exact network), tf32 (GPU), bf16 (autocast), onnx (ONNX Runtime, "
                                "exact), int8 (needs lcpr_quantize)", choices=PRECISIONS),
    "model.runtime": ParamDoc("what runs the exported graph (precision onnx / int8): auto (int8: the faster of "
                              "the two, measured at start; onnx: onnxruntime), onnxruntime, openvino",
                              choices=RUNTIMES),
    "model.device": ParamDoc("torch device, e.g. cpu or cuda:0"),
    "model.threads": ParamDoc("torch intra-op threads; 0 = torch's default", 0, 1024),
    "model.cuda_graph": ParamDoc("on a GPU, replay the network from a CUDA graph of one frame (or its six turns); "
                                 "false = eager passes"),
    "model.decode": ParamDoc("camera decoding: auto (nvjpeg on a GPU where torchvision imports, else turbo), turbo "
                             "(libjpeg-turbo at a reduced size, antialiased resize; CPU), nvjpeg (GPU), pil (the "
                             "released pipeline, slowest)", choices=DECODERS),
    "model.fast_decode": ParamDoc("with decode pil: JPEG draft-mode decoding (faster, slightly different pixels)"),
    "model.whitening": ParamDoc("apply the descriptor whitening stored in the weights file, when it has one "
                                "(the bundled weights do; lcpr_train --whiten)"),
    "model.turn_average": ParamDoc("average each descriptor over the six camera-slot turns (six network passes) "
                                   "when the weights file asks for it (the bundled weights do)"),
    # ---- keyframes and matching (may change at run time)
    "keyframe.min_interval": ParamDoc("s (header stamps) between keyframes", 0.0, 3600.0, dynamic=True),
    "keyframe.min_distance": ParamDoc("m travelled between keyframes when poses are known; 0 = off",
                                      0.0, 1e6, dynamic=True),
    "match.top_k": ParamDoc("candidates per query", 1, 1000, dynamic=True),
    "match.max_distance": ParamDoc("descriptor L2 distance a candidate must be under (unit vectors: 0..2); -1 = "
                                   "automatic: 1.0 with verification (every top-k candidate is checked), without it "
                                   "the weights file's operating threshold (bundled: 0.70; 1.0 for files without one)",
                                   -1.0, 2.0, dynamic=True),
    "match.exclude_recent_s": ParamDoc("this session's keyframes newer than this many seconds are not matched",
                                       0.0, 1e9, dynamic=True),
    "match.exclude_recent_count": ParamDoc("and neither are the last N keyframes; 0 = off", 0, BIG, dynamic=True),
    "match.method": ParamDoc("what proposes the candidates: lcpr (the descriptor), scan_context (the top_k nearest "
                             "Scan Contexts of the keyframes' clouds) or fused (both lists); the network runs for "
                             "all (docs/lidar_only.md compares them on real LiDARs)", choices=MATCH_METHODS),
    "match.sc_max_distance": ParamDoc("Scan Context distance (0..1) a scan_context / fused candidate must be under; "
                                      "1 = every top-k one (verification decides)", 0.0, 1.0, dynamic=True),
    "sensors.require_lidar": ParamDoc("no cloud -> no keyframe; false: an empty range image is used"),
    # ---- descriptor map (read-only: fixed by the map)
    "map.dim": ParamDoc("descriptor size stored in the map", 1, 65536),
    "map.descriptor_tag": ParamDoc("names what made the map's descriptors (the file header's 'model' field); a map "
                                   "file must carry the same tag (formerly map.model, still accepted with a warning)"),
    "map.index": ParamDoc("search structure", choices=INDEX_TYPES),
    "map.hnsw_m": ParamDoc("HNSW graph degree (map.index = hnsw)", 1, 1024),
    "map.hnsw_ef_search": ParamDoc("HNSW search breadth (map.index = hnsw)", 1, 1 << 20),
    "map.hnsw_ef_construction": ParamDoc("HNSW build breadth (map.index = hnsw)", 1, 1 << 20),
    "map.path": ParamDoc("descriptor map file (.npz), loaded at start when it exists and saved on ~/save_map "
                         "and at shutdown; empty = in memory only"),
    "session": ParamDoc("source name stored with this run's keyframes"),
    # ---- topics (read-only)
    "camera_topics": ParamDoc("camera image topics in rig (nuScenes) order"),
    "camera_type": ParamDoc("message type of the camera topics; auto: topics ending in /compressed are "
                            "sensor_msgs/CompressedImage, others sensor_msgs/Image", choices=CAMERA_TYPES),
    "lidar_topic": ParamDoc("sensor_msgs/PointCloud2 topic"),
    "odom_topic": ParamDoc("nav_msgs/Odometry topic for poses (markers, keyframe.min_distance); empty = none"),
    "lidar_only": ParamDoc("no camera subscriptions: every frame is described with all camera slots empty, "
                           "verified and published as usual (a vehicle with a LiDAR and no surround cameras)"),
    "tf_static_topic": ParamDoc("tf2_msgs/TFMessage topic the submap mount (submap.lidar_xyz / lidar_rpy) is read "
                                "from: the transform from the odometry's child frame to the clouds' frame, once "
                                "heard, replaces those parameters; needs tf2_msgs (a sourced ROS 2); empty = off"),
    # ---- synchronisation
    "sync.slop": ParamDoc("s: each camera's image nearest the cloud stamp within this is used", 0.0, 10.0,
                          dynamic=True),
    "sync.camera_timeout": ParamDoc("s of header time: a camera silent this long is stopped (frames degraded)",
                                    0.0, 3600.0, dynamic=True),
    "sync.max_wait": ParamDoc("s of wall time a cloud waits for camera images stamped after it", 0.0, 10.0,
                              dynamic=True),
    "sync.min_cameras": ParamDoc("frames with fewer camera images are dropped", 0, 64, dynamic=True),
    "sync.odom_max_gap": ParamDoc("s: odometry neighbours at most this far apart are interpolated", 0.0, 60.0,
                                  dynamic=True),
    "sync.image_buffer": ParamDoc("images kept per camera for matching", 1, 1000),
    "sync.max_pending": ParamDoc("clouds waiting for images at most; older ones are dropped", 1, 1000),
    "sync.jump_back": ParamDoc("s: a header stamp this much older than its stream's newest (a bag played again, "
                               "--loop, a simulator reset) starts a new session in the same map; 0 = refuse it "
                               "as out of order", 0.0, 86400.0),
    # ---- input_qos, map.save_on_shutdown, diagnostics: ros_common.config.SHARED_DOCS
}

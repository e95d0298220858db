"""The short synthetic KITTI-rig drive the VSeq2PC detector tests run: LiDAR scans, then camera frames of
the same route REVISIT s later (a second visit of every place)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from citysim import SynthConfig, SyntheticDrive
from lcpr_core.pretrained import default_vseq2pc_weights
from lcpr_core.vseq2pc import Vseq2pcNet
from lcpr_core.vseq2pc.detector import CameraFrame, LabelledScan

FRAMES = 16
DT = 0.25  # s between frames
REVISIT = 100.0  # s from a scan to the camera frame of the same place


def short_drive(**options: object) -> tuple[SyntheticDrive, list[LabelledScan], list[CameraFrame]]:
    """(the drive, its FRAMES labelled scans, its FRAMES camera frames of the revisit); ``options`` go to
    SynthConfig (e.g. depth_noise=0.0 for exact depth, drive=1 for another route through the same city)."""
    synth = SyntheticDrive(SynthConfig(rig="kitti", frames=FRAMES, route="grid", image_size=(320, 96), seed=0,
                                       camera_drop=0.0, keyframe_spacing=2.5, **options))  # type: ignore[arg-type]
    camera = synth.rig.cameras[0]
    scans, cameras = [], []
    for i in range(FRAMES):
        frame = synth.frame(i)
        image = frame.cameras[0]
        assert image is not None and image.depth is not None and image.labels is not None
        xyz = np.stack([frame.cloud[n] for n in "xyz"], axis=1).astype(np.float32)
        scans.append(LabelledScan(i * DT, xyz, frame.cloud["label"].astype(np.uint32), synth.pose(i)))
        cameras.append(CameraFrame(REVISIT + i * DT, image.depth.astype(np.float32), image.labels.astype(np.uint16),
                                   camera.K, synth.pose(i)))
    return synth, scans, cameras


@dataclass
class Drive:
    """The short drive as a detector test uses it: scans, camera frames, the camera's mount, the bundled network."""

    scans: list[LabelledScan]
    cameras: list[CameraFrame]
    lidar_T_cam: np.ndarray  # 4 x 4
    net: Vseq2pcNet

    @property
    def extrinsics(self) -> tuple[float, ...]:
        """``lidar_T_cam`` as SequenceDetectorConfig takes it (16 numbers, row-major)."""
        return tuple(self.lidar_T_cam.ravel().tolist())


def bundled_net() -> Vseq2pcNet:
    """The bundled VSeq2PC weights (part of the checkout)."""
    weights = default_vseq2pc_weights()
    assert weights is not None, "weights/vseq2pc_synth_*.pth are missing from this checkout"
    return Vseq2pcNet.from_files(sequence=weights[0], descriptor=weights[1])

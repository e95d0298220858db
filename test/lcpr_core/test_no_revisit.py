"""A drive that never comes back publishes no loop, whatever retrieval proposes."""
from __future__ import annotations

from typing import cast

import numpy as np
import pytest
import torch

from lcpr_core.detector import DetectorConfig, Frame, LoopDetector, MatchConfig
from lcpr_core.lcpr.describer import Describer, Prepared, prepare_each


class AnyPlace:
    """Stands in for the network: random unit descriptors, so every older keyframe is a candidate."""

    weights_id = "any-place-test"

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)

    def inputs(self, images, points):
        return torch.zeros(1), torch.zeros(1)

    def prepare(self, images, points):
        return Prepared(*self.inputs(images, points))

    def prepare_many(self, frames):
        return prepare_each(self.prepare, frames)

    def describe_tensors(self, images, ranges):
        v = self.rng.normal(size=256).astype(np.float32)
        return (v / np.linalg.norm(v))[None]


@pytest.mark.slow
def test_a_drive_without_revisits_publishes_no_loop_although_every_candidate_is_verified(shared) -> None:
    from citysim import SynthConfig, SyntheticDrive

    drive = SyntheticDrive(SynthConfig(rig="nuscenes", route="kitti00", frames=100, seed=21, image_size=(64, 32)))
    positions = np.asarray(drive.keyframes.xy, np.float64)
    stamps = np.asarray(drive.keyframes.stamps, np.float64)
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1)[np.subtract.outer(stamps, stamps) >= 30.0]
    assert gaps.min() > 20.0, "the test drive must not revisit a place"
    det = LoopDetector(DetectorConfig(match=MatchConfig(top_k=10, max_distance=2.0)),
                       describer=cast(Describer, AnyPlace()))  # it has what the detector reads of a Describer
    verdicts: dict[str, int] = {}
    loops = 0
    for frame in drive.frames(workers=2):
        result = det.process(Frame(stamp=frame.stamp, images=[None] * 6, points=frame.xyz, pose=frame.pose))
        loops += result.loop is not None
        for c in result.candidates:
            verdicts[c.verification] = verdicts.get(c.verification, 0) + 1
    assert sum(verdicts.values()) >= 200, verdicts  # retrieval did propose (wrong) places
    assert loops == 0 and "accepted" not in verdicts, verdicts

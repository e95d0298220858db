"""On the real nuScenes keyframe the descriptor is sane and robust to a turn of the vehicle."""
from __future__ import annotations

import numpy as np
import pytest

from lcpr_core import Describer, ModelConfig
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
from lcpr_offline.lcpr_keyframe_demo import cosine, main, yaw_and_degradation


@pytest.fixture(scope="module")
def keyframe(nuscenes_sample):
    return find_nuscenes_keyframe(nuscenes_sample).read()


@pytest.fixture(scope="module")
def describer():
    return Describer(ModelConfig(threads=2))


def test_the_keyframe_descriptor_is_finite_and_unit_length(keyframe, describer):
    images, points = keyframe
    desc = describer.describe(images, points)
    assert desc.shape == (256,) and desc.dtype == np.float32
    assert np.isfinite(desc).all()
    assert np.linalg.norm(desc) == pytest.approx(1.0, abs=1e-5)


def test_a_turn_by_one_camera_slot_moves_the_descriptor_far_less_than_moving_10_m(keyframe, describer):
    images, points = keyframe
    desc = describer.describe(images, points)
    changes = {label.split(" (")[0]: 1 - cosine(desc, d) for label, d in
               yaw_and_degradation(describer, images, points, desc).items()}
    turned, moved = changes["vehicle turned 60 deg"], changes["for contrast: the cloud seen from 10 m further on"]
    assert turned < 1e-5
    assert moved > 20 * turned


def test_the_demo_runs_with_the_bundled_weights_and_writes_its_figure(nuscenes_sample, tmp_path, capsys):
    assert main(["--data", str(nuscenes_sample), "--repeats", "1", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "weights: the bundled weights" in out and "lcpr_synth_narrow.pth" in out and "network fp32" in out
    assert (tmp_path / "demo_keyframe.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_demo_says_where_to_point_it_when_data_is_missing(tmp_path, capsys):
    assert main(["--data", str(tmp_path)]) == 2
    assert "pass --data" in capsys.readouterr().err

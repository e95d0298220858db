"""The CPU camera path that decodes, resizes and normalises each image in a pool thread: same input as the
batched resize, simplejpeg or OpenCV underneath, torch's threads left alone (the released-size descriptor is
checked in test_camera_decode)."""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from lcpr_core import Describer, ModelConfig, range_image
from lcpr_core.errors import InputShapeError, InvalidValueError
from lcpr_core.lcpr.preprocess import decode
from lcpr_core.lcpr.preprocess.cameras import CameraPreprocessor
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe


@pytest.fixture(scope="module")
def keyframes(shared: Path) -> list[tuple[list[bytes], np.ndarray]]:
    return [find_nuscenes_keyframe(shared / "data" / name).read() for name in ("nuscenes_sample", "nuscenes_sample2")]


def test_simplejpeg_and_opencv_decode_a_real_camera_image_to_nearly_the_same_pixels(keyframes):
    pytest.importorskip("simplejpeg")
    data = keyframes[0][0][0]
    fast = decode.decode_scaled(data, (256, 704), backend="simplejpeg")
    other = decode.decode_scaled(data, (256, 704), backend="opencv")
    assert fast.shape == other.shape == (450, 800, 3) and fast.dtype == np.uint8
    assert float(np.abs(fast.astype(np.int16) - other).mean()) < 1.0  # grey levels


def test_without_simplejpeg_opencv_decodes_and_the_benchmark_says_so(keyframes, monkeypatch):
    images, _ = keyframes[0]
    with_simplejpeg, _ = CameraPreprocessor(size=(64, 192), decoder="turbo")(images)
    monkeypatch.setattr(decode, "simplejpeg_module", lambda: None)
    assert decode.jpeg_backend().startswith("opencv")
    without, failed = CameraPreprocessor(size=(64, 192), decoder="turbo")(images)
    assert not failed and float((without - with_simplejpeg).abs().mean()) < 0.02  # normalised units
    with pytest.raises(InvalidValueError, match="'simplejpeg' is not installed"):
        decode.decode_scaled(images[0], (64, 192), backend="simplejpeg")


def test_an_unknown_jpeg_backend_is_refused_naming_the_accepted_ones(keyframes):
    with pytest.raises(InvalidValueError, match="'pillow'; accepted: auto, simplejpeg, opencv"):
        decode.decode_scaled(keyframes[0][0][0], (64, 192), backend="pillow")


@pytest.mark.parametrize("size", [(256, 704), (64, 192)])
def test_the_per_image_pool_path_gives_exactly_the_batched_resize_input(keyframes, size):
    cams = CameraPreprocessor(size=size, decoder="turbo")
    for images, _ in keyframes:
        fused, failed = cams(images)
        pixels, _ = cams.decode(images)
        batched = cams.assemble(pixels, len(images))
        assert not failed and fused.shape == (6, 3, *size)
        assert torch.allclose(fused, batched, atol=1e-6, rtol=0)


@pytest.mark.parametrize("size", [(256, 704), (64, 192)])
def test_a_missing_camera_slot_is_zero_and_the_others_filled(keyframes, size):
    images, _ = keyframes[0]
    out, failed = CameraPreprocessor(size=size, decoder="turbo")([images[0], None, *images[2:]])
    assert not failed
    assert out[1].abs().sum() == 0 and all(out[k].abs().sum() > 0 for k in (0, 2, 3, 4, 5))


def test_the_pool_threads_leave_the_callers_and_new_threads_torch_thread_count_alone(keyframes):
    images, _ = keyframes[0]
    before = torch.get_num_threads()
    CameraPreprocessor(size=(256, 704), decoder="turbo")(images)
    seen: list[int] = []
    thread = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
    thread.start()
    thread.join()
    assert torch.get_num_threads() == before and seen == [before]


@pytest.mark.parametrize(("size", "resizes"), [((256, 704), 6), ((64, 192), 1)])
def test_the_profile_gives_each_images_decode_and_each_resize_cpu_time(keyframes, size, resizes):
    images, _ = keyframes[0]
    cams = CameraPreprocessor(size=size, decoder="turbo")
    cams.profile = []
    cams(images)
    stages = [stage for stage, _ in cams.profile]
    assert stages.count("decode") == 6 and stages.count("resize + normalise") == resizes  # per image, or one batch
    assert all(seconds >= 0 for _, seconds in cams.profile)


def test_prepare_makes_the_range_image_beside_the_cameras_and_keeps_it_exact(keyframes):
    describer = Describer(ModelConfig(width=0.25, image_size=(64, 192), range_size=(32, 1056), precision="fp32",
                                      decode="turbo", seed=0))
    for images, points in keyframes:
        prepared = describer.prepare(images, points)
        assert np.array_equal(prepared.ranges[0, 0].numpy(), range_image(points, preset="nuscenes_lidar_top"))
        assert prepared.images.shape == (1, 6, 3, 64, 192) and not prepared.failed


def test_an_unusable_image_in_the_pool_path_leaves_its_slot_zero_and_says_which_and_why(keyframes):
    images, _ = keyframes[0]
    frame = [images[0], images[1][:5000], b"\xff\xd8\xffgarbage\xff\xd9", *images[3:]]
    cams = CameraPreprocessor(size=(256, 704), decoder="turbo")
    out, failed = cams(frame)
    assert sorted(failed) == [1, 2] and "truncated" in failed[1]
    assert all(out[k].abs().sum() == 0 for k in (1, 2)) and all(out[k].abs().sum() > 0 for k in (0, 3, 4, 5))
    with pytest.raises(InputShapeError, match="camera 1"):
        cams(frame, strict=True)

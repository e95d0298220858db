"""The fast camera path (reduced-size libjpeg-turbo decode, antialiased resize) keeps the released descriptor,
refuses bad images per camera, and the range image has one torch twin for the GPU."""
from __future__ import annotations

import dataclasses
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from PIL import Image

from lcpr_core import Describer, InputShapeError, ModelConfig, cameras_tensor, range_image
from lcpr_core.errors import DeviceError, InvalidValueError, RuntimeSetupError
from lcpr_core.lcpr.preprocess import PRESETS
from lcpr_core.lcpr.preprocess.cameras import CameraPreprocessor, resolve_decoder
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
from lcpr_core.lcpr.preprocess.decode import jpeg_size, reduction
from lcpr_core.lcpr.preprocess.range_image import NO_RETURN, range_image_tensor, range_images_tensor
from lcpr_core.lcpr.runtime.numerics import float32_math
from lcpr_core.pretrained import default_weights

SMALL: dict[str, Any] = dict(width=0.25, image_size=(64, 192), range_size=(16, 264), precision="fp32")


def jpeg(h: int = 900, w: int = 1600, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, size=(h // 50 + 1, w // 50 + 1, 3), dtype=np.uint8)
    image = np.kron(coarse, np.ones((50, 50, 1), np.uint8))[:h, :w]
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=90)
    return buf.getvalue()


@pytest.fixture(scope="module")
def keyframes(shared: Path) -> list[tuple[list[bytes], np.ndarray]]:
    return [find_nuscenes_keyframe(shared / "data" / name).read() for name in ("nuscenes_sample", "nuscenes_sample2")]


@pytest.fixture(scope="module")
def bundled() -> Describer:
    weights = default_weights()
    assert weights is not None, "the bundled weights are part of the package"
    return Describer(ModelConfig(weights=str(weights), precision="fp32", decode="turbo"))


def assert_within_cosine_of_pil(fast: Describer, keyframes: list[tuple[list[bytes], np.ndarray]]) -> None:
    """``fast``'s descriptor of each real keyframe within cosine 0.9999 of the same network's on PIL's pixels."""
    reference = Describer(dataclasses.replace(fast.config, decode="pil"), model=fast.model)
    for images, points in keyframes:
        got, want = fast.describe(images, points), reference.describe(images, points)
        assert float(np.dot(got, want)) >= 0.9999


def test_the_fast_decoder_keeps_the_bundled_descriptor_within_cosine_0_9999_on_both_real_keyframes(
        keyframes, bundled):
    assert_within_cosine_of_pil(bundled, keyframes)


@pytest.mark.slow
def test_the_released_size_descriptor_stays_within_cosine_0_9999_of_pil_on_both_real_keyframes(keyframes):
    # the released input sizes (256 x 704 images, 32 x 1056 range image), a quarter-width seeded network
    fast = Describer(ModelConfig(width=0.25, precision="fp32", decode="turbo", seed=0))
    assert fast.config.image_size == (256, 704)
    assert_within_cosine_of_pil(fast, keyframes)


def test_the_fast_decoder_keeps_the_released_size_input_close_to_the_pil_pixels(keyframes):
    images, _ = keyframes[0]
    fast, failed = CameraPreprocessor(size=(256, 704), decoder="turbo")(images)
    reference = cameras_tensor(images, size=(256, 704))
    assert not failed and fast.shape == reference.shape == (6, 3, 256, 704)
    assert float((fast - reference).abs().mean()) < 0.02  # normalised units: about 1 grey level


def test_the_decoder_reduces_as_far_as_the_target_size_allows():
    assert reduction(900, 1600, (256, 704)) == 2
    assert reduction(900, 1600, (64, 192)) == 8
    assert reduction(900, 1600, (900, 1600)) == 1
    assert reduction(360, 640, (256, 704)) == 1


def test_the_jpeg_header_gives_the_size_and_a_cut_file_is_refused_as_truncated():
    data = jpeg(90, 160)
    assert jpeg_size(data) == (90, 160)
    with pytest.raises(InputShapeError, match="truncated"):
        jpeg_size(data[: len(data) // 2])
    with pytest.raises(InputShapeError, match="not a JPEG"):
        jpeg_size(b"GIF89a....")


@pytest.mark.parametrize("decoder", ["turbo", "pil"])
def test_an_unusable_camera_image_leaves_its_slot_empty_and_says_which_and_why(decoder: str):
    good = jpeg(90, 160)
    cams = CameraPreprocessor(size=(32, 64), decoder=decoder)
    out, failed = cams([good, good[:300], b"\xff\xd8\xffgarbage\xff\xd9", None, np.zeros((4, 4), np.uint8)])
    assert sorted(failed) == [1, 2, 4]
    assert "truncated" in failed[1] or "truncated" in failed[1].lower()
    assert out.shape == (5, 3, 32, 64)
    assert out[0].abs().sum() > 0 and all(out[k].abs().sum() == 0 for k in (1, 2, 3, 4))
    with pytest.raises(InputShapeError, match="camera 1"):
        cams([good, good[:300]], strict=True)


def test_images_of_different_sizes_in_one_frame_are_each_resized():
    cams = CameraPreprocessor(size=(32, 64), decoder="turbo")
    out, failed = cams([jpeg(90, 160), jpeg(120, 200, seed=1), np.full((40, 70, 3), 7, np.uint8)])
    assert not failed and out.shape == (3, 3, 32, 64)
    reference = cameras_tensor([jpeg(90, 160), jpeg(120, 200, seed=1), np.full((40, 70, 3), 7, np.uint8)],
                               size=(32, 64))
    assert float((out - reference).abs().mean(dim=(1, 2, 3)).max()) < 0.05  # each slot: its own image


def test_the_detector_path_counts_a_corrupt_camera_as_missing_and_still_describes_the_frame():
    from lcpr_core.detector import DetectorConfig, Frame, LoopDetector

    det = LoopDetector(DetectorConfig(model=ModelConfig(**SMALL, seed=0)))
    points = np.random.default_rng(0).uniform(-30, 30, size=(2000, 3)).astype(np.float32)
    good = jpeg(90, 160)
    result = det.process(Frame(stamp=0.0, images=[good, good[:200], good, good, good, good], points=points))
    assert result.keyframe_id == 0 and result.missing_cameras == (1,)
    assert "truncated" in result.camera_errors[1]


def test_decoder_names_are_checked_and_nvjpeg_needs_a_gpu():
    with pytest.raises(InvalidValueError, match="accepted: auto, pil, turbo, nvjpeg"):
        ModelConfig(decode="fast")
    with pytest.raises(InvalidValueError, match="needs model.device cuda"):
        resolve_decoder("nvjpeg", "cpu")
    assert resolve_decoder("auto", "cpu") == "turbo"


def test_the_torch_range_image_matches_the_numpy_one_on_the_real_sweeps_but_for_border_points(keyframes):
    """The torch projection (used on a GPU) against the numpy reference (used on the CPU).

    Exact equality is not a property of the arithmetic on the CPU: torch's sqrt there goes through
    MKL, which is not correctly rounded for every element and, depending on thread state, sometimes
    runs a less accurate variant for one thread's share. A point sitting on a pixel border may then
    change pixel. So: every pixel but a handful equal, bit for bit; the GPU's equality is checked in
    test_cuda.py.
    """
    for _, points in keyframes:
        for name in ("nuscenes_lidar_top", "kitti_hdl64e"):
            expected = range_image(points, preset=name)
            got = range_image_tensor(torch.from_numpy(points), preset=PRESETS[name]).numpy()
            assert got.dtype == np.float32 and got.shape == expected.shape
            differing = int(np.count_nonzero(got != expected))
            assert differing <= 8, f"{name}: {differing} of {expected.size} pixels differ"


def test_several_clouds_projected_in_one_pass_each_give_their_own_range_image(keyframes):
    first, second = (points for _, points in keyframes)
    broken = second.copy()
    broken[::7, 0] = np.nan  # non-finite points are dropped, as in one cloud alone
    clouds = [first, np.zeros((0, 3), np.float32), broken]
    got = range_images_tensor([torch.from_numpy(c) for c in clouds], preset=PRESETS["nuscenes_lidar_top"]).numpy()
    assert got.shape == (3, 32, 1056)
    assert (got[1] == NO_RETURN).all()  # an empty cloud: no return anywhere, nothing from its neighbours
    for k in (0, 2):
        differing = int(np.count_nonzero(got[k] != range_image(clouds[k], preset="nuscenes_lidar_top")))
        assert differing <= 8, f"cloud {k}: {differing} pixels differ"  # MKL's sqrt at pixel borders (above)
    with pytest.raises(InputShapeError, match="expected at least one"):
        range_images_tensor([], preset=PRESETS["nuscenes_lidar_top"])


def test_frames_decoded_together_equal_each_frame_decoded_alone_and_keep_their_own_failures(keyframes):
    images, _ = keyframes[0]
    other, _ = keyframes[1]
    broken = [None, *other[1:3], other[3][:300], *other[4:]]  # camera 0 missing, camera 3 truncated
    cams = CameraPreprocessor(size=(64, 192), decoder="turbo")
    together, failed = cams.many([images, broken])
    assert together.shape == (2, 6, 3, 64, 192)
    assert failed[0] == {} and sorted(failed[1]) == [3] and "truncated" in failed[1][3]
    for b, frame in enumerate((images, broken)):
        alone, _ = cams(frame)
        torch.testing.assert_close(together[b], alone, atol=0, rtol=0)
    with pytest.raises(InputShapeError, match=r"\[5, 6\] camera slots"):
        cams.many([images, images[:5]])


def test_the_describer_prepares_several_frames_as_it_prepares_each(keyframes, bundled):
    batch = bundled.prepare_many(keyframes)
    assert batch.images.shape == (2, 6, 3, 64, 192) and batch.ranges.shape[:2] == (2, 1)
    assert batch.failed == [{}, {}]
    for b, (images, points) in enumerate(keyframes):
        alone = bundled.prepare(images, points)
        torch.testing.assert_close(batch.images[b:b + 1], alone.images, atol=0, rtol=0)
        torch.testing.assert_close(batch.ranges[b:b + 1], alone.ranges, atol=0, rtol=0)


def test_tf32_is_refused_on_the_cpu_naming_what_runs_there():
    with pytest.raises(RuntimeSetupError, match="tf32.*needs a CUDA device.*accepted on the CPU"):
        Describer(ModelConfig(**{**SMALL, "precision": "tf32"}))


def test_the_float32_switches_are_restored_after_a_pass():
    conv: Any = torch.backends.cudnn.conv  # type: ignore[attr-defined]
    before = conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision
    with float32_math(tf32=False):
        assert conv.fp32_precision == "ieee"
    with float32_math(tf32=True):
        assert conv.fp32_precision == "tf32"
    assert (conv.fp32_precision, torch.backends.cuda.matmul.fp32_precision) == before


def test_a_device_out_of_memory_is_a_skipped_frame_not_a_crash(monkeypatch):
    describer = Describer(ModelConfig(**SMALL))
    images, ranges = describer.inputs([jpeg(90, 160)] * 6, np.zeros((10, 3), np.float32))

    def out_of_memory(*_: object) -> np.ndarray:
        raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")

    monkeypatch.setattr(describer, "backend", out_of_memory)
    with pytest.raises(DeviceError, match="ran out of memory describing 1 frame"):
        describer.describe_tensors(images, ranges)

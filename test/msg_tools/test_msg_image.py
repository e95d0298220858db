"""Image, CompressedImage and CameraInfo conversions: roundtrips over encodings and padding, and errors."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from camera_encodings import blocky_rgb, mosaic, nv21, packed_yuv422, smooth_rgb
from msg_tools import (
    CameraInfoError,
    CameraModel,
    ImageEncodingError,
    ImageLayoutError,
    array_to_compressed,
    array_to_image,
    camera_info_to_model,
    compressed_jpeg_bytes,
    compressed_to_array,
    depth_to_metres,
    image_to_array,
    image_to_rgb,
    model_to_camera_info,
)
from msg_tools.compressed import compressed_bytes, encode_image
from msg_tools.image import ENCODINGS, PACKED_YUV_ENCODINGS
from msg_tools.types import message_class

Image = message_class("sensor_msgs/msg/Image")
Header = message_class("std_msgs/msg/Header")
Time = message_class("builtin_interfaces/msg/Time")


def _pixels(encoding: str, height: int, width: int, seed: int) -> np.ndarray:
    enc = ENCODINGS[encoding]
    rng = np.random.default_rng(seed)
    shape = (height, width) if enc.channels == 1 else (height, width, enc.channels)
    if enc.dtype.kind == "f":
        values = rng.normal(scale=10.0, size=shape).astype(enc.dtype)
        values[rng.random(shape) < 0.1] = np.nan
        return values
    info = np.iinfo(enc.dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=enc.dtype)


def _message(pixels: np.ndarray, encoding: str, *, pad: int, bigendian: bool) -> Any:
    """Pack rows by hand (with ``pad`` junk bytes after each row), independently of the code under test."""
    stored = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<"))
    rows = [stored[r].tobytes() + b"\xab" * pad for r in range(pixels.shape[0])]
    step = len(rows[0]) if rows else pad
    return Image(
        header=Header(stamp=Time(sec=3, nanosec=4), frame_id="cam"), height=pixels.shape[0], width=pixels.shape[1],
        encoding=encoding, is_bigendian=int(bigendian), step=step,
        data=np.frombuffer(b"".join(rows), dtype=np.uint8),
    )


@settings(max_examples=60, deadline=None)
@given(
    encoding=st.sampled_from(sorted(ENCODINGS)),
    height=st.integers(1, 5),
    width=st.integers(1, 6),
    pad=st.integers(0, 9),
    bigendian=st.booleans(),
    seed=st.integers(0, 2**31),
)
def test_every_encoding_reads_back_through_row_padding_and_roundtrips(
    encoding: str, height: int, width: int, pad: int, bigendian: bool, seed: int
) -> None:
    if encoding in PACKED_YUV_ENCODINGS:
        width *= 2  # two pixels share their chroma
    pixels = _pixels(encoding, height, width, seed)
    got = image_to_array(_message(pixels, encoding, pad=pad, bigendian=bigendian))
    assert got.dtype == pixels.dtype and got.dtype.isnative and got.shape == pixels.shape
    assert np.array_equal(got, pixels, equal_nan=pixels.dtype.kind == "f")
    again = array_to_image(got, encoding=encoding, frame_id="cam", stamp=1.0)
    assert np.array_equal(image_to_array(again), pixels, equal_nan=pixels.dtype.kind == "f")


def test_colour_encodings_all_become_the_same_rgb() -> None:
    rgb = _pixels("rgb8", 4, 5, 1)
    alpha = np.full((4, 5, 1), 9, dtype=np.uint8)
    variants = {
        "rgb8": rgb, "bgr8": rgb[:, :, ::-1], "rgba8": np.concatenate([rgb, alpha], axis=2),
        "bgra8": np.concatenate([rgb[:, :, ::-1], alpha], axis=2),
    }
    for encoding, pixels in variants.items():
        assert np.array_equal(image_to_rgb(array_to_image(pixels, encoding=encoding, frame_id="c", stamp=0.0)), rgb)
    grey = image_to_rgb(array_to_image(np.full((2, 2), 513, np.uint16), encoding="mono16", frame_id="c", stamp=0.0))
    assert grey.shape == (2, 2, 3) and np.all(grey == 2)


def test_depth_becomes_metres_with_zero_for_unknown() -> None:
    mm = np.array([[0, 1500], [20, 65535]], dtype=np.uint16)
    metres = depth_to_metres(array_to_image(mm, encoding="16UC1", frame_id="c", stamp=0.0))
    assert metres.dtype == np.float32 and np.allclose(metres, [[0, 1.5], [0.02, 65.535]])
    raw = np.array([[np.nan, 2.5], [-1.0, np.inf]], dtype=np.float32)
    assert depth_to_metres(
        array_to_image(raw, encoding="32FC1", frame_id="c", stamp=0.0)
    ).tolist() == [[0, 2.5], [0, 0]]
    with pytest.raises(ImageEncodingError, match="not a depth encoding"):
        depth_to_metres(array_to_image(_pixels("rgb8", 2, 2, 0), encoding="rgb8", frame_id="c", stamp=0.0))


def test_an_unknown_encoding_is_refused_with_the_accepted_ones() -> None:
    msg = _message(_pixels("mono8", 2, 2, 0), "yuv420p", pad=0, bigendian=False)
    with pytest.raises(ImageEncodingError, match="'yuv420p' is not supported; accepted: rgb8, bgr8"):
        image_to_array(msg)


def test_step_and_data_length_errors_name_the_numbers() -> None:
    msg = _message(_pixels("mono16", 2, 3, 0), "mono16", pad=0, bigendian=False)
    msg.step = 5
    with pytest.raises(ImageLayoutError, match="step 5 is smaller than .* = 6"):
        image_to_array(msg)
    msg.step, msg.data = 6, msg.data[:-1]
    with pytest.raises(ImageLayoutError, match="11 bytes, fewer than step \\* height"):
        image_to_array(msg)


def test_an_array_that_does_not_fit_its_encoding_is_refused() -> None:
    with pytest.raises(ImageEncodingError, match="holds uint16 pixels but the array is float32"):
        array_to_image(np.zeros((2, 2), np.float32), encoding="16UC1", frame_id="c", stamp=0.0)
    with pytest.raises(ImageLayoutError, match="needs an H x W x 3 array"):
        array_to_image(np.zeros((2, 2), np.uint8), encoding="rgb8", frame_id="c", stamp=0.0)


def test_png_roundtrips_exactly_and_jpeg_approximately() -> None:
    yy, xx = np.mgrid[0:24, 0:32]
    rgb = np.stack([xx * 8, yy * 10, (xx + yy) * 4], axis=2).astype(np.uint8)
    png = array_to_compressed(rgb, format="png", frame_id="c", stamp=2.0)
    assert png.format == "png" and np.array_equal(compressed_to_array(png), rgb)
    mono16 = (xx * 1000).astype(np.uint16)
    assert np.array_equal(
        compressed_to_array(array_to_compressed(mono16, format="png", frame_id="c", stamp=0.0)), mono16
    )
    jpeg = array_to_compressed(rgb, format="jpeg", quality=95, frame_id="c", stamp=2.0)
    decoded = compressed_to_array(jpeg)
    assert decoded.shape == rgb.shape and np.abs(decoded.astype(int) - rgb).mean() < 3
    assert image_to_rgb(jpeg).shape == rgb.shape


def test_original_jpeg_bytes_are_kept_byte_for_byte() -> None:
    data = encode_image(np.zeros((8, 8, 3), np.uint8), format="jpeg")
    msg = compressed_jpeg_bytes(data, frame_id="CAM_FRONT", stamp=1.0)
    assert compressed_bytes(msg) == data and msg.format == "jpeg"
    with pytest.raises(ImageEncodingError, match="expected JPEG bytes"):
        compressed_jpeg_bytes(encode_image(np.zeros((8, 8), np.uint8), format="png"), frame_id="c", stamp=0.0)


def test_compressed_bytes_that_contradict_their_format_are_refused() -> None:
    msg = array_to_compressed(np.zeros((4, 4, 3), np.uint8), format="png", frame_id="c", stamp=0.0)
    msg.format = "jpeg"
    with pytest.raises(ImageEncodingError, match="names jpeg but the bytes are png"):
        compressed_to_array(msg)
    msg.data = np.frombuffer(b"GIF89a....", np.uint8)
    with pytest.raises(ImageEncodingError, match="neither JPEG"):
        compressed_to_array(msg)


def _model() -> CameraModel:
    K = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, 3] = [1.7, 0.0, 1.5]
    return CameraModel("CAM_FRONT", "CAM_FRONT", 1600, 900, K, pose)


def test_a_camera_model_roundtrips_through_camera_info() -> None:
    model = _model()
    info = model_to_camera_info(model, stamp=5.0)
    assert info.header.frame_id == "CAM_FRONT" and info.p[3] == 0.0
    back = camera_info_to_model(info, name="CAM_FRONT", base_T_cam=model.base_T_cam)
    assert (back.width, back.height, back.frame_id) == (1600, 900, "CAM_FRONT")
    assert np.array_equal(back.K, model.K) and np.array_equal(back.base_T_cam, model.base_T_cam)


def test_camera_info_with_distortion_or_a_bad_matrix_is_refused() -> None:
    info = model_to_camera_info(_model(), stamp=0.0)
    info.d = np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(CameraInfoError, match="distortion \\[0.1"):
        camera_info_to_model(info, name="CAM_FRONT")
    assert camera_info_to_model(info, name="CAM_FRONT", ignore_distortion=True).width == 1600
    info.k = np.zeros(9)
    with pytest.raises(CameraInfoError, match="not a pinhole matrix"):
        camera_info_to_model(info, name="CAM_FRONT", ignore_distortion=True)


def test_rclpy_images_and_camera_info_convert_too() -> None:
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    pixels = _pixels("bgr8", 3, 4, 2)
    msg = array_to_image(pixels, encoding="bgr8", frame_id="cam", stamp=7.5, msg_type=sensor_msgs.Image)
    assert isinstance(msg, sensor_msgs.Image) and msg.step == 12
    assert np.array_equal(image_to_array(msg), pixels) and np.array_equal(image_to_rgb(msg), pixels[:, :, ::-1])

    hand_made = sensor_msgs.Image(height=1, width=2, encoding="mono16", is_bigendian=1, step=6)
    hand_made.data = b"\x01\x02\x03\x04\xff\xff"  # big-endian pixels plus 2 padding bytes
    assert image_to_array(hand_made).tolist() == [[0x0102, 0x0304]]

    jpeg = array_to_compressed(pixels, frame_id="cam", stamp=1.0, msg_type=sensor_msgs.CompressedImage)
    assert isinstance(jpeg, sensor_msgs.CompressedImage) and compressed_to_array(jpeg).shape == (3, 4, 3)

    info = model_to_camera_info(_model(), stamp=1.0, msg_type=sensor_msgs.CameraInfo)
    assert isinstance(info, sensor_msgs.CameraInfo)
    assert np.array_equal(camera_info_to_model(info, name="CAM_FRONT").K, _model().K)


# ---------------------------------------------------------------------- camera-native encodings
@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_a_bayer_mosaic_is_demosaiced_into_the_colours_it_sampled(pattern: str) -> None:
    encoding = f"bayer_{pattern}8"
    flat = np.empty((8, 10, 3), np.uint8)
    flat[:] = (200, 90, 20)  # a colour with three different channels: a wrong pattern swaps them
    got = image_to_rgb(array_to_image(mosaic(flat, pattern), encoding=encoding, frame_id="c", stamp=0.0))
    assert got.shape == (8, 10, 3) and got.dtype == np.uint8
    assert np.abs(got[2:-2, 2:-2].astype(int) - flat[2:-2, 2:-2]).max() <= 1, got[4, 4]
    smooth = smooth_rgb(24, 32)
    got = image_to_rgb(array_to_image(mosaic(smooth, pattern), encoding=encoding, frame_id="c", stamp=0.0))
    assert np.abs(got[2:-2, 2:-2].astype(int) - smooth[2:-2, 2:-2]).max() <= 4


@pytest.mark.parametrize("encoding, order", [("yuv422", "UYVY"), ("uyvy", "UYVY"), ("yuv422_yuy2", "YUYV"),
                                             ("yuyv", "YUYV")])
def test_packed_yuv_422_becomes_the_rgb_it_encodes(encoding: str, order: str) -> None:
    rgb = blocky_rgb(6, 8)
    got = image_to_rgb(array_to_image(packed_yuv422(rgb, order), encoding=encoding, frame_id="c", stamp=0.0))
    assert got.shape == rgb.shape
    assert np.abs(got.astype(int) - rgb).max() <= 3


def test_nv21_becomes_the_rgb_it_encodes() -> None:
    rgb = blocky_rgb(6, 8)
    msg = array_to_image(nv21(rgb), encoding="nv21", frame_id="c", stamp=0.0)
    assert (msg.height, msg.width, msg.step) == (6, 8, 8)
    assert image_to_array(msg).shape == (9, 8)
    assert np.abs(image_to_rgb(msg).astype(int) - rgb).max() <= 3


@pytest.mark.parametrize("encoding, height, width, shown", [
    ("yuv422", 4, 5, "even width"), ("nv21", 5, 8, "must be even"),
])
def test_odd_sizes_of_subsampled_encodings_are_refused_with_the_size_named(encoding, height, width, shown) -> None:
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id="c"), height=height, width=width,
                encoding=encoding, is_bigendian=0, step=2 * width, data=np.zeros(4 * height * width, np.uint8))
    with pytest.raises(ImageLayoutError, match=shown):
        image_to_rgb(msg)


def test_an_nv21_image_without_its_chroma_plane_is_refused() -> None:
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id="c"), height=4, width=4, encoding="nv21",
                is_bigendian=0, step=4, data=np.zeros(16, np.uint8))  # the Y plane only
    with pytest.raises(ImageLayoutError, match="fewer than step"):
        image_to_array(msg)


def test_an_unknown_encoding_lists_the_camera_native_ones_too() -> None:
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id="c"), height=2, width=2, encoding="bayer_xyzw8",
                is_bigendian=0, step=2, data=np.zeros(4, np.uint8))
    with pytest.raises(ImageEncodingError, match="bayer_rggb8.*nv21"):
        image_to_rgb(msg)


@pytest.mark.parametrize("encoding", ["bayer_rggb8", "bayer_grbg8", "yuv422", "yuyv", "nv21"])
@pytest.mark.parametrize("height, width", [(0, 4), (4, 0), (0, 0)])
def test_an_empty_camera_native_image_with_data_becomes_an_empty_rgb_array(encoding, height, width) -> None:
    """Found by fuzzing: OpenCV's cvtColor asserts on an empty input, so msg_tools must not hand it one."""
    msg = Image(header=Header(stamp=Time(sec=1, nanosec=0), frame_id="c"), height=height, width=width,
                encoding=encoding, is_bigendian=0, step=8, data=np.arange(64, dtype=np.uint8))
    rgb = image_to_rgb(msg)
    assert rgb.shape == (height, width, 3) and rgb.dtype == np.uint8

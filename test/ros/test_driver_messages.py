"""Clouds and images as real drivers publish them are read exactly, or refused naming what is wrong."""
from __future__ import annotations

import numpy as np
import pytest

from driver_layouts import LAYOUTS, driver_cloud, scan
from lcpr_core.lcpr.preprocess import range_image
from msg_tools import pointcloud2_to_array
from ros_common import inputs
from ros_common.errors import InputRejected


def _rows(name: str) -> int:
    return max(LAYOUTS[name].rows, 16)


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_every_driver_layout_gives_exactly_its_returned_points(name: str) -> None:
    layout = LAYOUTS[name]
    xyz, valid = scan(_rows(name), 512 if layout.rows <= 64 else 256, seed=1)
    points, nonfinite = inputs.cloud_points(driver_cloud(layout, xyz, valid))
    assert points.dtype == np.float32 and points.shape == (int(valid.sum()), 3)
    assert np.allclose(points, xyz[valid], atol=1e-5)
    assert nonfinite == (int((~valid).sum()) if layout.invalid == "nan" else 0)  # zeros are no fault


@pytest.mark.parametrize("name", ["ouster_os1_64", "velodyne_hdl32_organised"])
def test_missing_returns_never_become_range_image_pixels(name: str) -> None:
    """An organised cloud marks missing beams with zeros (Ouster) or NaN: the range image holds only returns."""
    layout = LAYOUTS[name]
    xyz, valid = scan(layout.rows, 512, seed=2, missing=0.5)
    points, _ = inputs.cloud_points(driver_cloud(layout, xyz, valid))
    got = range_image(points, preset="velodyne_vlp16", height=layout.rows, width=512)
    sent = xyz[valid].astype(np.float32)  # what the message carries
    expected = range_image(sent, preset="velodyne_vlp16", height=layout.rows, width=512)
    assert np.array_equal(got, expected)
    assert np.count_nonzero(got > 0) <= int(valid.sum())
    assert (got[got >= 0] > 1.0).all()  # no pixel at the origin's range


def test_an_organised_ouster_cloud_keeps_its_shape_and_driver_fields() -> None:
    layout = LAYOUTS["ouster_os1_64"]
    xyz, valid = scan(64, 1024, seed=3)
    array = pointcloud2_to_array(driver_cloud(layout, xyz, valid))
    assert array.shape == (64, 1024) and array.dtype.itemsize == 48
    assert array.dtype.names is not None
    assert set(array.dtype.names) == {"x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"}
    assert array["ring"].dtype == np.uint16 and array["t"].dtype == np.uint32
    returned = valid.reshape(64, 1024)
    assert (array["range"][~returned] == 0).all() and (array["range"][returned] > 0).all()


def test_a_big_endian_cloud_reads_the_same_points() -> None:
    layout = LAYOUTS["hesai_pandar64"]
    xyz, valid = scan(16, 256, seed=4)
    little, _ = inputs.cloud_points(driver_cloud(layout, xyz, valid))
    big, _ = inputs.cloud_points(driver_cloud(layout, xyz, valid, bigendian=True))
    assert np.array_equal(little, big)


def test_a_cloud_whose_xyz_are_float64_is_read_too() -> None:
    from driver_layouts import DriverLayout

    layout = DriverLayout("f64", (("x", "f8", 0), ("y", "f8", 8), ("z", "f8", 16), ("intensity", "f4", 24)), 32, 1,
                          "absent")
    xyz, valid = scan(16, 128, seed=5)
    points, _ = inputs.cloud_points(driver_cloud(layout, xyz, valid))
    assert np.allclose(points, xyz[valid], atol=1e-5)


def test_a_cloud_without_z_is_refused_naming_its_fields() -> None:
    from driver_layouts import DriverLayout

    layout = DriverLayout("xy", (("x", "f4", 0), ("y", "f4", 4), ("intensity", "f4", 8)), 12, 1, "absent")
    xyz, valid = scan(16, 64, seed=6)
    with pytest.raises(InputRejected, match=r"no field\(s\) \['z'\].*'intensity'"):
        inputs.cloud_points(driver_cloud(layout, xyz, valid))

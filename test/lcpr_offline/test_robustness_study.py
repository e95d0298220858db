"""The LCPR robustness study's perturbations (lcpr_offline.lcpr_robustness): what each one removes; the LiDAR
occlusion study's rule (lcpr_core.lcpr.training.recipe_rules.lidar_occlusion_replaces)."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import torch

from lcpr_core.lcpr.describer import Describer
from lcpr_core.lcpr.preprocess.range_image import NO_RETURN
from lcpr_core.lcpr.training.recipe_rules import lidar_occlusion_replaces
from lcpr_offline.lcpr_robustness import Keyframe, camera_out, lidar_quarter_out, parse_city, plot


class EchoDescriber:
    """Stands in for a Describer: the 'descriptor' is the range image the perturbation handed to the model."""

    def inputs(self, images: Any, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.zeros(1, 6, 3, 4, 4), torch.arange(1.0, 16 * 288 + 1).view(1, 1, 16, 288)

    def describe_tensors(self, images: torch.Tensor, ranges: torch.Tensor) -> np.ndarray:
        return ranges.numpy().reshape(1, 16, 288)


def occluded(part: str) -> np.ndarray:
    kf = Keyframe(0.0, [None] * 6, np.zeros((1, 3)), np.zeros(3))
    return lidar_quarter_out(part)(cast(Describer, EchoDescriber()), kf)


@pytest.mark.parametrize(("part", "rows", "columns"), [("columns", slice(None), slice(0, 72)),
                                                       ("top rows", slice(0, 4), slice(None)),
                                                       ("bottom rows", slice(12, 16), slice(None))])
def test_each_lidar_occlusion_blanks_exactly_its_quarter_of_the_range_image(part: str, rows: slice,
                                                                           columns: slice) -> None:
    out = occluded(part)
    blank = np.zeros(out.shape, bool)
    blank[rows, columns] = True
    assert np.all(out[blank] == NO_RETURN) and np.all(out[~blank] != NO_RETURN)
    assert blank.mean() == pytest.approx(0.25)


class ImagesDescriber:
    """Stands in for a Describer: the 'descriptor' says which camera slots received an image."""

    def describe(self, images: list[Any], points: np.ndarray) -> np.ndarray:
        return np.array([im is not None for im in images])


@pytest.mark.parametrize(("index", "sent"), [(2, [1, 1, 0, 1, 1, 1]), (None, [0] * 6)])
def test_a_camera_out_blanks_its_slot_and_all_cameras_out_leaves_the_lidar_alone(index: int | None,
                                                                                  sent: list[int]) -> None:
    kf = Keyframe(0.0, [np.zeros((2, 2, 3), np.uint8)] * 6, np.zeros((1, 3)), np.zeros(3))
    assert camera_out(index)(cast(Describer, ImagesDescriber()), kf).astype(int).tolist() == sent


def test_an_unknown_lidar_part_names_the_accepted_ones() -> None:
    with pytest.raises(ValueError, match="'left half'.*'columns', 'top rows', 'bottom rows'"):
        occluded("left half")


def test_a_city_may_name_its_own_keyframe_count() -> None:
    assert parse_city("grid:7") == ("grid", 7, None)
    assert parse_city("kitti00:21:900") == ("kitti00", 21, 900)
    for bad in ("grid", "moon:3", "grid:7:x", "grid:7:300:1"):
        with pytest.raises(argparse.ArgumentTypeError, match="ROUTE:SEED"):
            parse_city(bad)


def test_the_study_plot_draws_a_subset_of_the_studies(tmp_path: Path) -> None:
    results = {"grid:3": {"occlusion": {"none": 0.9, "LiDAR 1/4 top rows out": 0.2}}}
    plot(results, tmp_path / "r.png", weights="w.pth")
    assert (tmp_path / "r.png").stat().st_size > 1000


@pytest.mark.parametrize(("clean", "quarters", "expected"), [
    (0.90, 0.60, True),  # robust, no clean loss
    (0.895, 0.60, True),  # half a point of clean recall lost: allowed
    (0.88, 0.60, False),  # two points lost: kept out
    (0.92, 0.40, False),  # more clean recall, but no more robust
])
def test_occlusion_trained_weights_replace_the_bundled_only_under_the_fixed_rule(clean: float, quarters: float,
                                                                                expected: bool) -> None:
    bundled = {"mean_recall@1": 0.90, "mean_lidar_quarter_recall@1": 0.40}
    new = {"mean_recall@1": clean, "mean_lidar_quarter_recall@1": quarters}
    assert lidar_occlusion_replaces(bundled, new) is expected

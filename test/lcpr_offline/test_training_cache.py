"""Preprocessing once: the cache holds what inference preprocessing makes, and is reused."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from citysim import SynthConfig, SyntheticDrive, write_bag
from lcpr_core.lcpr.preprocess import cameras_tensor, range_image
from lcpr_core.lcpr.training import InputConfig, TrainingData
from lcpr_core.lcpr.training.cache import CacheError
from lcpr_offline.lcpr_cache import build_cache
from lcpr_offline.lcpr_train import main as train_main
from msg_tools import NUSCENES_TOPICS, read_frames

SMALL = InputConfig(image_size=(32, 96), range_size=(8, 144), width=0.25)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("synth") / "tiny.bag"
    write_bag(SyntheticDrive(SynthConfig(frames=3, seed=3, image_size=(200, 112))), path, workers=1)
    return path


def test_the_cache_holds_the_inference_preprocessing_of_every_frame(bag, tmp_path):
    cache = build_cache([bag], tmp_path / "cache", inputs=SMALL, progress=False)
    assert len(cache) == 3 and cache.images.dtype == np.uint8 and cache.ranges.dtype == np.float16
    data = TrainingData(cache=cache, split=None)  # type: ignore[arg-type]  # inputs() needs no split
    images, ranges = data.inputs([0, 1, 2])
    for i, frame in enumerate(read_frames(bag, topics=NUSCENES_TOPICS)):
        want = cameras_tensor([None if c is None else c.jpeg for c in frame.cameras], size=SMALL.image_size)
        assert torch.allclose(images[i], want, atol=1e-5)
        rng = range_image(frame.xyz, height=8, width=144)
        assert np.allclose(ranges[i, 0].numpy(), rng, atol=0.05)
        assert frame.pose is not None
        assert np.allclose(cache.poses[i], frame.pose)


def test_an_up_to_date_cache_is_reused_and_a_new_size_rebuilds_it(bag, tmp_path):
    first = build_cache([bag], tmp_path / "cache", inputs=SMALL, progress=False)
    mtime = (first.folder / "images.npy").stat().st_mtime_ns
    again = build_cache([bag], tmp_path / "cache", inputs=SMALL, progress=False)
    assert (again.folder / "images.npy").stat().st_mtime_ns == mtime
    bigger = build_cache([bag], tmp_path / "cache", inputs=InputConfig(image_size=(64, 192)), progress=False)
    assert bigger.images.shape[2:4] == (64, 192)


def test_a_missing_bag_is_named(tmp_path):
    with pytest.raises(CacheError, match="nope.bag"):
        build_cache([tmp_path / "nope.bag"], tmp_path / "cache", inputs=SMALL, progress=False)


def test_the_cli_explains_a_drive_without_revisits(bag, tmp_path, capsys):
    code = train_main([str(bag), "--out", str(tmp_path / "run"), "--image-size", "32", "96", "--range-size",
                       "8", "144", "--quiet"])
    assert code == 2
    assert "training needs train and val queries" in capsys.readouterr().err


def test_several_workers_make_the_same_cache_as_one_process(bag, tmp_path):
    other = tmp_path / "other.bag"
    write_bag(SyntheticDrive(SynthConfig(frames=2, seed=4, image_size=(200, 112))), other, workers=1)
    one = build_cache([bag, other], tmp_path / "one", inputs=SMALL, progress=False)
    two = build_cache([bag, other], tmp_path / "two", inputs=SMALL, progress=False, workers=2)
    assert len(two) == 5 and two.groups.tolist() == [0, 0, 0, 1, 1]
    for name in ("images", "cameras", "ranges", "poses", "stamps", "groups"):
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    assert two.meta["samples_per_bag"] == one.meta["samples_per_bag"] == [3, 2]
    assert {p.name for p in (tmp_path / "two").iterdir()} == {p.name for p in (tmp_path / "one").iterdir()}
    again = build_cache([bag, other], tmp_path / "two", inputs=SMALL, progress=False, workers=2)
    assert (again.folder / "images.npy").stat().st_mtime_ns == (two.folder / "images.npy").stat().st_mtime_ns


def test_zero_workers_are_refused_by_name(bag, tmp_path):
    with pytest.raises(CacheError, match="workers=0"):
        build_cache([bag], tmp_path / "cache", inputs=SMALL, progress=False, workers=0)

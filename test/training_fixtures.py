"""Tiny hand-made training data for the training tests: a cache folder written with numpy, no bag."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lcpr_core.lcpr.training import InputConfig, OptimConfig, SplitConfig, TrainConfig

TINY = InputConfig(num_cameras=2, image_size=(32, 64), range_size=(8, 64), width=0.125)


def out_and_back(n: int = 24, step: float = 5.0, dt: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Drive n/2 samples east along a street and back: the return leg revisits every place."""
    half = n // 2
    x = np.r_[np.arange(half) * step, (half - 1 - np.arange(n - half)) * step + 1.0]
    return np.stack([x, np.zeros(n)], axis=1), np.arange(n) * dt


def write_tiny_cache(folder: Path, *, inputs: InputConfig = TINY, bags: int = 1, seed: int = 0) -> Path:
    """A cache folder of `bags` out-and-back drives whose inputs depend on the place (x) only, plus noise."""
    rng = np.random.default_rng(seed)
    pos, stamps = out_and_back()
    n = len(stamps) * bags
    c, (h, w), (rh, rw) = inputs.num_cameras, inputs.image_size, inputs.range_size
    place = np.tile(np.round(pos[:, 0] / 10.0), bags)  # coarse place id
    base = rng.integers(0, 256, size=(int(place.max()) + 1, bags, c, h, w, 3))
    groups = np.repeat(np.arange(bags), len(stamps)).astype(np.int32)
    images = np.clip(base[place.astype(int), groups] + rng.integers(-20, 21, size=(n, c, h, w, 3)), 0, 255)
    ranges = (5.0 + place[:, None, None] + rng.uniform(0, 1, size=(n, rh, rw))).astype(np.float16)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :2, 3] = np.tile(pos, (bags, 1))
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "images.npy", images.astype(np.uint8))
    np.save(folder / "cameras.npy", np.ones((n, c), bool))
    np.save(folder / "ranges.npy", ranges)
    np.save(folder / "poses.npy", poses)
    np.save(folder / "stamps.npy", np.tile(stamps, bags) + 1.7e9)
    np.save(folder / "groups.npy", groups)
    (folder / "meta.json").write_text(json.dumps({"version": 1, "inputs": {}, "bags": []}))
    return folder


def tiny_config(*, epochs: int = 1, lr: float = 1e-3) -> TrainConfig:
    return TrainConfig(inputs=TINY, split=SplitConfig(fractions=(0.6, 0.2, 0.2)),
                       optim=OptimConfig(epochs=epochs, lr=lr, queries_per_batch=2, queries_per_epoch=4),
                       threads=1, eval_batch=8)

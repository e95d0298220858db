"""Shared fixtures: the reference material and real frames in ../shared beside the checkout."""
from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import pytest

from lcpr_common.shared_data import shared_dir

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def _graph_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Exported ONNX graphs of seeded test models go to a cache of this run, not the user's."""
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg_cache"))


def reference_sets(method: str) -> list[Path]:
    """The authors' parity vectors of ``method`` (lcpr | vseq2pc), one file per seed; [] without ../shared."""
    found = shared_dir(marker="reference")
    return sorted((found / "reference" / method).glob("expected_seed*.npz")) if found else []


def reference_seed(ref_file: Path) -> int:
    """The seed a parity-vector file was made with (``expected_seed<N>.npz``)."""
    found = re.search(r"seed(\d+)", ref_file.stem)
    assert found is not None, f"{ref_file.name} does not name its seed"
    return int(found.group(1))


@pytest.fixture(scope="session")
def shared() -> Path:
    found = shared_dir(marker="reference")
    if found is None:
        message = "../shared (reference vectors and real frames) not found beside the checkout; set LCPR_SHARED_DIR"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return found


@pytest.fixture(scope="session")
def detweights(shared: Path):
    """The authors' deterministic-weights module (reference material, not project code)."""
    sys.path.insert(0, str(shared / "reference"))
    try:
        import detweights as module
    finally:
        sys.path.pop(0)
    return module


@pytest.fixture(scope="session")
def nuscenes_sample(shared: Path) -> Path:
    return shared / "data" / "nuscenes_sample"

"""Finding ../shared: one rule for the simulator, the demo, the benchmarks and the fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

from lcpr_common import shared_data
from lcpr_common.shared_data import shared_dir, shared_path

REPO = Path(__file__).resolve().parents[2]


def test_the_environment_variable_comes_before_the_folder_beside_the_checkout(tmp_path, monkeypatch) -> None:
    (tmp_path / "data" / "kitti00").mkdir(parents=True)
    (tmp_path / "data" / "kitti00" / "poses.txt").write_text("")
    monkeypatch.setenv(shared_data.ENV_VAR, str(tmp_path))
    assert shared_data.shared_candidates()[0] == tmp_path
    assert shared_dir() == tmp_path
    assert shared_path("data", "kitti00", "poses.txt") == tmp_path / "data" / "kitti00" / "poses.txt"


def test_without_the_variable_shared_beside_the_checkout_is_found_from_any_working_directory(
        tmp_path, monkeypatch) -> None:
    if not (REPO.parent / "shared" / "data").is_dir():
        pytest.skip("this checkout has no ../shared beside it")
    monkeypatch.delenv(shared_data.ENV_VAR, raising=False)
    monkeypatch.chdir(tmp_path)
    assert shared_dir() == REPO.parent / "shared"
    from citysim.drive import default_kitti_poses
    assert default_kitti_poses().is_file()


def test_a_path_found_nowhere_is_named_under_the_first_candidate(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(shared_data.ENV_VAR, str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert shared_path("data", "no_such_set") == tmp_path / "data" / "no_such_set"
    assert shared_dir(marker="no_such_marker") is None

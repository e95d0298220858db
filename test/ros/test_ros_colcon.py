"""The package builds with colcon (ament_python) and the installed lcpr_node runs."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "lcpr_loop_closure"
COPY_IGNORE = shutil.ignore_patterns(".git", ".venv", "build", "install", "log", "out", "__pycache__", "*.egg-info",
                                     ".hypothesis", ".pytest_cache", "*.pyc", "shared")


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    colcon = shutil.which("colcon")
    if colcon is None:
        pytest.skip("colcon is not on PATH (Debian: apt-get install -y colcon); the colcon build is not tested")
    ws = tmp_path_factory.mktemp("ws")
    # a copy, not a symlink: setuptools writes egg-info beside setup.py and must not touch the checkout
    shutil.copytree(REPO, ws / "src" / PACKAGE, ignore=COPY_IGNORE)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COLCON", "AMENT", "PYTHON"))}
    done = subprocess.run(
        [colcon, "build", "--base-paths", "src", "--build-base", "build", "--install-base", "install",
         "--event-handlers", "console_direct-"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=600,
    )
    assert done.returncode == 0, f"colcon build failed:\n{done.stdout[-4000:]}\n{done.stderr[-4000:]}"
    return ws / "install" / PACKAGE


def site_packages(prefix: Path) -> Path:
    found = sorted(prefix.glob("lib/python3*/site-packages"))
    assert found, f"no site-packages under {prefix / 'lib'}"
    return found[0]


def run_installed(prefix: Path, *command: str, **extra_env: str) -> subprocess.CompletedProcess[str]:
    """Run with this venv's interpreter (it has torch, faiss, rclpy) and the installed package first on the path."""
    env = {**os.environ, **extra_env,
           "PYTHONPATH": os.pathsep.join([str(site_packages(prefix)), sysconfig.get_paths()["purelib"]])}
    return subprocess.run([sys.executable, *command], cwd=prefix, env=env, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_colcon_installs_the_executables_the_params_file_and_the_launch_file(installed: Path) -> None:
    for exe in ("lcpr_node", "lcpr_replay", "lcpr_backend", "lcpr_kiss_icp"):
        assert (installed / "lib" / PACKAGE / exe).is_file(), f"{exe} not installed under lib/{PACKAGE}"
    share = installed / "share" / PACKAGE
    assert (share / "package.xml").is_file()
    assert (share / "config" / "lcpr.yaml").is_file()
    assert (share / "launch" / "lcpr.launch.xml").is_file()
    assert (share / "launch" / "lcpr_backend.launch.xml").is_file()
    assert (share / "config" / "lcpr_backend.yaml").is_file()
    assert (installed / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()


@pytest.mark.slow
def test_the_installed_lcpr_node_runs_from_the_install_tree(installed: Path) -> None:
    where = run_installed(installed, "-c", "import lcpr_ros, lcpr_core, backend_ros; "
                          "print(lcpr_ros.__file__, lcpr_core.__file__, backend_ros.__file__)")
    assert where.returncode == 0, where.stderr
    assert all(path.startswith(str(installed)) for path in where.stdout.split()), where.stdout
    done = run_installed(installed, str(installed / "lib" / PACKAGE / "lcpr_node"), "--help")
    assert done.returncode == 0, done.stderr
    assert "lcpr_node" in done.stdout and "match.top_k" in done.stdout
    refused = run_installed(installed, str(installed / "lib" / PACKAGE / "lcpr_node"),
                            "--ros-args", "-p", "match.top_k:=0")
    assert refused.returncode == 1 and "match.top_k out of range" in refused.stdout + refused.stderr


@pytest.mark.slow
def test_the_installed_package_finds_its_bundled_weights_through_the_ament_prefix(installed: Path) -> None:
    script = "from lcpr_core.pretrained import default_weights; print(default_weights())"
    done = run_installed(installed, "-c", script, AMENT_PREFIX_PATH=str(installed))  # as a sourced install sets it
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(installed / "share" / PACKAGE / "weights" / "lcpr_synth_narrow.pth")

"""The lcpr node as a separate process (python -m lcpr_ros.node --ros-args ...), over real DDS on loopback."""
from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from rclpy.node import Node

from lcpr_core.descriptor_map import DescriptorMap
from ros_common import inputs
from ros_common.harness import (
    FramePublisher,
    OutputListener,
    cloud_with_nan,
    cloud_without_xyz,
    driver_node,
    image_of_wrong_size,
    image_with_unknown_encoding,
    synthetic_place,
    truncated_cloud,
    wait_until,
)

REPO = Path(__file__).resolve().parents[2]
DOMAIN = random.randint(1, 100)
PREFIX = f"/p{random.randint(0, 10**6)}"
CAMERAS = [f"{PREFIX}/CAM_{k}/image_raw" for k in range(6)]  # no /compressed: auto -> sensor_msgs/Image
LIDAR = f"{PREFIX}/LIDAR_TOP/points"
T0 = 1_600_000_000.0
WAIT = 60.0

PARAMS = f"""lcpr:
  ros__parameters:
    model:
      weights: seeded
      image_size: [32, 96]
      lidar: velodyne_vlp16
      range_size: [8, 256]
      width: 0.25
    camera_topics: [{", ".join(CAMERAS)}]
    lidar_topic: {LIDAR}
    sync:
      camera_timeout: 5.0
    diagnostics:
      period: 0.2
"""


class NodeProcess:
    """``python -m lcpr_ros.node`` with its output in a file."""

    def __init__(self, log: Path, *ros_args: str) -> None:
        self.log = log
        env = {**os.environ, "ROS_DOMAIN_ID": str(DOMAIN), "PYTHONPATH": os.pathsep.join(
            [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]), "PYTHONUNBUFFERED": "1"}
        self._out = log.open("wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "lcpr_ros.node", "--ros-args", *ros_args],
                                     cwd=REPO, env=env, stdout=self._out, stderr=subprocess.STDOUT)

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for(self, pattern: str, timeout: float = WAIT) -> re.Match[str]:
        found: list[re.Match[str]] = []

        def seen() -> bool:
            match = re.search(pattern, self.text())
            if match:
                found.append(match)
            return bool(match) or self.proc.poll() is not None

        assert wait_until(seen, timeout) and found, f"{pattern!r} not in the node's output:\n{self.text()}"
        return found[0]

    def stop(self, sig: int = signal.SIGTERM, timeout: float = WAIT) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait(10)
            self._out.close()


def run_node(tmp_path: Path, *ros_args: str, timeout: float = WAIT) -> tuple[int, str]:
    """Run a node that is expected to exit by itself (refused start)."""
    node = NodeProcess(tmp_path / f"refused{random.randint(0, 10**9)}.log", *ros_args)
    try:
        rc = node.proc.wait(timeout)
    finally:
        if node.proc.poll() is None:
            node.proc.kill()
    return rc, node.text()


@dataclass
class Driver:
    node: Node
    pub: FramePublisher
    listener: OutputListener

    def processed(self) -> int:
        values = self.listener.latest_values("detector")
        return sum(int(v) for k, v in values.items() if k.startswith("frames "))

    def feed(self, place_number: int, stamp: float, skip: tuple[int, ...] = ()) -> None:
        before = self.processed()
        self.pub.publish(synthetic_place(place_number), stamp, skip_cameras=skip)
        assert wait_until(lambda: self.processed() > before), f"frame {stamp} was not processed"


@pytest.fixture(scope="module")
def driver() -> Iterator[Driver]:
    with driver_node("process_driver", DOMAIN) as node:
        yield Driver(node, FramePublisher(node, CAMERAS, LIDAR, compressed=False), OutputListener(node))


@pytest.fixture()
def workdir(tmp_path: Path) -> Path:
    (tmp_path / "small.yaml").write_text(PARAMS)
    return tmp_path


def start(workdir: Path, name: str, driver: Driver, *extra: str) -> NodeProcess:
    driver.listener.clear()  # a previous node's outputs and counts must not be read as this one's
    node = NodeProcess(workdir / f"{name}.log", "--params-file", str(workdir / "small.yaml"),
                       "-p", f"map.path:={workdir / 'map.npz'}", "--log-level", "lcpr:=debug", *extra)
    node.wait_for(r"\[lcpr\]: ready")
    driver.pub.wait_for_subscribers()
    driver.listener.wait_for_publishers()
    assert wait_until(lambda: bool(driver.listener.latest_values("detector")), 20)
    return node


@pytest.fixture()
def first_run(workdir: Path, driver: Driver) -> Iterator[NodeProcess]:
    """A node process of its own for every test (fresh map file, log and counters)."""
    node = start(workdir, "first", driver)
    yield node
    node.stop()


@pytest.mark.slow
def test_the_node_process_matches_an_exact_revisit_on_both_output_topics(first_run: NodeProcess,
                                                                          driver: Driver) -> None:
    for i in range(3):
        driver.feed(i, T0 + i)
    driver.feed(2, T0 + 35.0)
    out = driver.listener.out
    assert driver.listener.wait(lambda o: bool(o.loops) and bool(o.candidates), 10)
    assert out.loops == [(pytest.approx(T0 + 35.0), pytest.approx(T0 + 2.0))]
    best = out.candidates[-1][0]
    assert (best["query_id"], best["match_id"], best["rank"]) == (3, 2, 0)
    assert best["distance"] == pytest.approx(0.0, abs=1e-4)


@pytest.mark.slow
def test_bad_input_to_the_process_is_warned_once_per_cause_counted_in_diagnostics_and_the_map_kept(
        first_run: NodeProcess, driver: Driver) -> None:
    pub, place = driver.pub, synthetic_place(1)
    for i in range(2):  # earlier places, more than 30 s before the degraded frames: they get candidates
        driver.feed(i, T0 + i)
    t = T0 + 40.0

    def dropped(cause: str) -> int:
        return int(driver.listener.latest_values("inputs").get(f"dropped {cause}", "0"))

    for repeat in range(3):
        t += 1.0
        pub.lidar.publish(cloud_without_xyz(t))
        pub.lidar.publish(truncated_cloud(place, t + 0.1))
        pub.cameras[0].publish(image_with_unknown_encoding(t, compressed=False))
        pub.cameras[1].publish(image_of_wrong_size(t, compressed=False))
        # sensor-data QoS keeps the last 5 messages per topic: the next round waits until this one is counted
        causes = (inputs.CLOUD_NO_XYZ, inputs.CLOUD_TRUNCATED, inputs.IMAGE_ENCODING, inputs.IMAGE_SIZE)

        def counted(repeat: int = repeat, causes: tuple[str, ...] = causes) -> bool:
            return all(dropped(c) >= repeat + 1 for c in causes)
        assert wait_until(counted, 10)
    t += 1.0
    driver.feed(1, t)
    pub.publish(place, t)  # duplicate stamps
    pub.publish(place, t - 0.5)  # out of order
    t += 1.0
    before = driver.processed()
    for k, cam in enumerate(pub.cameras):
        cam.publish(pub.image_msg(place, k, t))
    pub.lidar.publish(cloud_with_nan(place, t, count=50))
    assert wait_until(lambda: driver.processed() > before)
    driver.feed(1, t + 3.0, skip=(4,))
    driver.feed(1, t + 6.0, skip=(4,))  # camera 4 silent for 6 s > sync.camera_timeout

    expected = {inputs.CLOUD_NO_XYZ: 3, inputs.CLOUD_TRUNCATED: 3, inputs.IMAGE_ENCODING: 3, inputs.IMAGE_SIZE: 3,
                "cloud: duplicate stamp": 1, "cloud: out of order": 1, "image: duplicate stamp": 6,
                "image: out of order": 6}
    assert wait_until(lambda: all(dropped(c) == n for c, n in expected.items()), 10), \
        {k: v for k, v in driver.listener.latest_values("inputs").items() if not k.startswith(("rate", "received"))}
    values = driver.listener.latest_values("inputs")
    assert values[inputs.CLOUD_NAN] == "50"
    assert values["stopped cameras"] == CAMERAS[4] and values["degraded"] == "1"
    assert int(values[f"frames without {CAMERAS[4]}"]) == 2

    log = first_run.text()
    for cause in [*expected, inputs.CLOUD_NAN, f"camera stopped: {CAMERAS[4]}"]:
        assert log.count(f"{cause}: ") == 1, f"{cause!r} warned {log.count(f'{cause}: ')} times:\n{log}"
    assert first_run.proc.poll() is None  # still up
    assert int(driver.listener.latest_values("detector")["map size"]) == 2 + 4  # the good frames went in
    assert driver.listener.out.candidates[-1][0]["degraded"] == 1


@pytest.mark.slow
def test_sigterm_finishes_the_frame_in_progress_saves_it_and_a_restart_keeps_every_keyframe(
        workdir: Path, first_run: NodeProcess, driver: Driver) -> None:
    for i in range(3):
        driver.feed(i, T0 + i)
    stamp = T0 + 60.0
    driver.pub.publish(synthetic_place(0), stamp)
    first_run.wait_for(rf"frame {stamp:.9f}: deciding")
    assert first_run.stop(signal.SIGTERM) == 0
    saved = DescriptorMap.load(workdir / "map.npz")
    assert len(saved) == 4 and saved.stamps[-1] == pytest.approx(stamp)  # the frame in progress is kept
    assert "saved 4 places" in first_run.text()

    second = start(workdir, "second", driver, "-p", "session:=second")
    try:
        second.wait_for(r"with 4 places")
        driver.feed(1, T0 + 61.0)  # prior-session places are never excluded by time
        assert driver.listener.wait(
            lambda o: bool(o.candidates) and o.candidates[-1][0]["query_stamp"] == pytest.approx(T0 + 61.0), 10)
        best = driver.listener.out.candidates[-1][0]
        assert best["query_id"] == 4 and best["distance"] == pytest.approx(0.0, abs=1e-4)
        assert best["match_id"] in saved.ids.tolist()
    finally:
        assert second.stop(signal.SIGINT) == 0
    reloaded = DescriptorMap.load(workdir / "map.npz")
    assert reloaded.ids.tolist() == [*saved.ids.tolist(), 4]
    assert reloaded.sources[-1] == "second" and reloaded.sources[0] == "session"


def test_a_corrupt_map_file_is_refused_with_a_nonzero_exit_and_left_unchanged(workdir: Path) -> None:
    corrupt = workdir / "corrupt.npz"
    corrupt.write_bytes(b"not a descriptor map at all")
    rc, text = run_node(workdir, "--params-file", str(workdir / "small.yaml"), "-p", f"map.path:={corrupt}")
    assert rc != 0
    assert "refusing to start" in text and str(corrupt) in text
    assert corrupt.read_bytes() == b"not a descriptor map at all"


@pytest.mark.parametrize(("args", "reason"), [
    (["-p", "match.top_k:=0"], "match.top_k out of range"),
    (["-p", "model.precision:=fp16"], "accepted: fp32, tf32, bf16"),
    (["-p", "camera_topics:=[/a,/b]"], "camera_topics names 2 topics but model.num_cameras=6"),
])
def test_invalid_parameters_refuse_the_start_with_a_reason_and_a_nonzero_exit(
        workdir: Path, args: list[str], reason: str) -> None:
    rc, text = run_node(workdir, *args)
    assert rc == 1
    assert "cannot start" in text and reason in text

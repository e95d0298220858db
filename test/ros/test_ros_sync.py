"""The nodes' pure-Python parts: synchronisation, odometry poses, the worker and its queue, statistics."""
from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import pytest

from lcpr_ros.config import SyncConfig
from lcpr_ros.sync import BACKLOG, NO_CAMERA, Synchroniser
from ros_common.poses import NoPoses, OdometryBuffer
from ros_common.stamps import DUPLICATE, OUT_OF_ORDER
from ros_common.stats import RateMeter, WarnOnce, Window
from ros_common.worker import DropOldestQueue, Worker

MS = 1_000_000
S = 1_000_000_000
POINTS = np.zeros((5, 3), np.float32)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def make_sync(cameras: int = 3, clock: FakeClock | None = None, **options: Any) -> Synchroniser:
    return Synchroniser(SyncConfig(**options), cameras, clock=clock or FakeClock())


def test_a_cloud_gets_the_nearest_image_of_each_camera_within_the_slop() -> None:
    sync = make_sync(2, slop=0.05)
    for ms in (960, 990, 1040):
        sync.offer_image(0, ms * MS, f"a{ms}")
    for ms in (900, 1020):
        sync.offer_image(1, ms * MS, f"b{ms}")
    sync.offer_cloud(1000 * MS, POINTS)
    (frame,) = sync.ready()
    assert frame.cameras == ["a990", "b1020"]
    assert frame.stamp_ns == 1000 * MS and frame.stopped == ()


def test_an_image_outside_the_slop_leaves_the_camera_empty_and_counts_it_missing() -> None:
    sync = make_sync(2, slop=0.01)
    sync.offer_image(0, 1000 * MS, "a")
    sync.offer_image(1, 1030 * MS, "b")
    sync.offer_cloud(1000 * MS, POINTS)
    (frame,) = sync.ready()
    assert frame.cameras == ["a", None]
    assert sync.missing == [0, 1]


def test_a_cloud_waits_for_images_stamped_after_it_until_they_arrive() -> None:
    sync = make_sync(2, slop=0.05, max_wait=10.0)
    sync.offer_image(0, 1000 * MS, "a")
    sync.offer_image(1, 980 * MS, "b-early")
    sync.offer_cloud(1000 * MS, POINTS)
    assert sync.ready() == [] and sync.pending == 1  # camera 1 may still send a nearer image
    sync.offer_image(1, 1005 * MS, "b-late")
    (frame,) = sync.ready()
    assert frame.cameras == ["a", "b-late"]


def test_a_cloud_goes_with_what_is_there_once_max_wait_wall_seconds_pass() -> None:
    clock = FakeClock()
    sync = make_sync(2, clock, slop=0.05, max_wait=0.2)
    sync.offer_image(0, 1000 * MS, "a")
    sync.offer_image(1, 990 * MS, "b")
    sync.offer_cloud(1000 * MS, POINTS)
    assert sync.ready() == []
    clock.now = 0.25
    (frame,) = sync.ready()
    assert frame.cameras == ["a", "b"]


def test_a_camera_silent_longer_than_the_timeout_is_stopped_and_the_frame_degraded() -> None:
    clock = FakeClock()
    sync = make_sync(2, clock, slop=0.05, camera_timeout=1.0, max_wait=0.5)
    sync.offer_image(0, 1000 * MS, "a0")
    sync.offer_image(1, 1000 * MS, "b0")
    sync.offer_cloud(1000 * MS, POINTS)
    assert [f.cameras for f in sync.ready()] == [["a0", "b0"]]
    sync.offer_image(0, 1500 * MS, "a1")
    sync.offer_cloud(1500 * MS, POINTS)
    assert sync.ready() == []  # camera 1 is 0.5 s behind: it may still deliver
    clock.now = 0.3
    sync.offer_image(0, 2100 * MS, "a2")
    sync.offer_cloud(2100 * MS, POINTS)  # camera 1 now 1.1 s behind in header time ...
    assert sync.ready() == []  # ... but it sent something 0.3 s ago (wall): a jump in stamps, not a stop
    clock.now = 0.6
    frames = sync.ready()  # nothing from camera 1 for 0.6 s > max_wait: stopped
    assert [f.cameras for f in frames] == [["a1", None], ["a2", None]]
    assert frames[-1].stopped == (1,)
    assert sync.stopped_cameras() == (1,)
    assert sync.missing == [0, 2]


def test_a_camera_that_never_sends_is_stopped_once_clouds_span_the_timeout() -> None:
    sync = make_sync(2, camera_timeout=1.0, max_wait=10.0)
    for t in (0, 600, 1200):
        sync.offer_image(0, t * MS, "a")
        sync.offer_cloud(t * MS, POINTS)
    frames = sync.ready()
    # the first two wait for camera 1; the third shows it stopped, so all three go (in order)
    assert sync.pending == 0
    assert [f.cameras for f in frames] == [["a", None]] * 3


def test_frames_with_fewer_than_min_cameras_images_are_dropped_and_counted() -> None:
    clock = FakeClock()
    sync = make_sync(3, clock, min_cameras=2, max_wait=0.1)
    sync.offer_image(0, 1000 * MS, "a")
    sync.offer_cloud(1000 * MS, POINTS)
    clock.now = 1.0
    assert sync.ready() == []
    assert sync.drops[NO_CAMERA] == 1


def test_duplicate_and_out_of_order_stamps_are_refused_per_stream() -> None:
    sync = make_sync(1)
    assert sync.offer_image(0, 10 * S, "a") is None
    assert sync.offer_image(0, 10 * S, "a") == DUPLICATE
    assert sync.offer_image(0, 9 * S, "a") == OUT_OF_ORDER
    assert sync.offer_cloud(10 * S, POINTS) is None
    assert sync.offer_cloud(10 * S, POINTS) == DUPLICATE
    assert sync.offer_cloud(5 * S, POINTS) == OUT_OF_ORDER


def test_at_most_max_pending_clouds_wait_and_older_ones_are_dropped() -> None:
    sync = make_sync(1, max_pending=2, max_wait=10.0, camera_timeout=100.0)
    sync.offer_image(0, 0, "a")
    for t in (1, 2, 3, 4):
        sync.offer_cloud(t * S, POINTS)
    assert sync.pending == 2
    assert sync.drops[BACKLOG] == 2


def test_image_buffers_are_bounded() -> None:
    sync = make_sync(1, image_buffer=4)
    for t in range(100):
        sync.offer_image(0, t * MS, t)
    assert len(sync._images[0]) == 4


def test_changing_the_config_at_run_time_resizes_the_buffers() -> None:
    sync = make_sync(1, image_buffer=8)
    for t in range(8):
        sync.offer_image(0, t * MS, t)
    sync.config = SyncConfig(image_buffer=3, slop=0.5)
    assert [p for _, p in sync._images[0]] == [5, 6, 7]


def test_odometry_is_interpolated_at_the_cloud_stamp() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0)
    for t, x in ((0, 0.0), (S, 10.0)):
        pose = np.eye(4)
        pose[0, 3] = x
        assert odom.offer(t, pose, "odom") is None
    sync = Synchroniser(SyncConfig(), 1, poses=odom, clock=FakeClock())
    sync.offer_image(0, S // 4, "a")
    sync.offer_cloud(S // 4, POINTS)
    (frame,) = sync.ready()
    assert frame.pose is not None and frame.pose[0, 3] == pytest.approx(2.5)
    assert odom.frame_id == "odom"
    assert odom.offer(S // 2, np.eye(4), "odom") == OUT_OF_ORDER


def test_a_cloud_waits_for_odometry_stamped_at_or_after_it() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0)
    sync = Synchroniser(SyncConfig(max_wait=10.0), 1, poses=odom, clock=FakeClock())
    odom.offer(0, np.eye(4), "odom")
    sync.offer_image(0, S, "a")
    sync.offer_cloud(S, POINTS)
    assert sync.ready() == []  # odometry of the cloud's time is still to come
    pose = np.eye(4)
    pose[1, 3] = 3.0
    odom.offer(S, pose, "odom")
    (frame,) = sync.ready()
    assert frame.pose is not None and frame.pose[1, 3] == 3.0


def test_silent_odometry_does_not_hold_clouds_back() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0)
    sync = Synchroniser(SyncConfig(max_wait=10.0, camera_timeout=1.0), 1, poses=odom, clock=FakeClock())
    for t in (0, 600, 1200):
        sync.offer_image(0, t * MS, "a")
        sync.offer_cloud(t * MS, POINTS)
    assert len(sync.ready()) == 3  # no odometry for 1.2 s of clouds: it is not waited for
    assert all(f.pose is None for f in sync.ready())


def test_without_odometry_poses_are_unknown() -> None:
    sync = Synchroniser(SyncConfig(), 1, poses=NoPoses(), clock=FakeClock())
    sync.offer_image(0, S, "a")
    sync.offer_cloud(S, POINTS)
    (frame,) = sync.ready()
    assert frame.pose is None


def test_the_odometry_buffer_stays_bounded() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0, capacity=10)
    for t in range(100):
        odom.offer(t * MS, np.eye(4), "odom")
    assert len(odom) <= 20
    assert odom.pose_at(99 * MS) is not None


# -- worker -------------------------------------------------------------------------------------
def test_the_slot_keeps_only_the_newest_item() -> None:
    slot: DropOldestQueue[int] = DropOldestQueue(1)
    assert slot.put(1) == []
    assert slot.put(2) == [1]
    assert slot.take(0.1) == 2
    assert slot.take(0.01) is None


def test_a_longer_queue_keeps_the_newest_items_in_order_and_drops_the_oldest() -> None:
    queue: DropOldestQueue[int] = DropOldestQueue(3)
    dropped = [d for i in range(5) for d in queue.put(i)]
    assert dropped == [0, 1] and len(queue) == 3
    assert [queue.take(0.1) for _ in range(3)] == [2, 3, 4]
    assert queue.close(keep=False) == [] and queue.put(9) == [9]


def test_a_busy_worker_drops_older_waiting_frames_and_never_queues_more_than_one() -> None:
    started, release = threading.Event(), threading.Event()
    handled: list[int] = []
    replaced: list[int] = []

    def handle(item: int) -> None:
        started.set()
        release.wait(5)
        handled.append(item)

    worker: Worker[int] = Worker(handle, on_dropped=replaced.append)
    worker.start()
    worker.submit(0)
    assert started.wait(5)
    for i in range(1, 6):
        worker.submit(i)
        assert worker.waiting <= 1
    release.set()
    assert worker.stop(drain=True, timeout=5)
    assert handled == [0, 5]
    assert replaced == [1, 2, 3, 4]


def test_stopping_the_worker_finishes_the_current_frame_first() -> None:
    done: list[int] = []
    started = threading.Event()

    def handle(item: int) -> None:
        started.set()
        time.sleep(0.2)  # a frame's work
        done.append(item)

    worker: Worker[int] = Worker(handle)
    worker.start()
    worker.submit(1)
    assert started.wait(5)
    assert worker.stop(drain=False, timeout=5)
    assert done == [1]


def test_an_exception_in_one_frame_does_not_end_the_worker() -> None:
    errors: list[str] = []
    done: list[int] = []

    def handle(item: int) -> None:
        if item == 1:
            raise RuntimeError("bad frame")
        done.append(item)

    failed = threading.Event()

    def on_error(item: int, err: Exception) -> None:
        errors.append(str(err))
        failed.set()

    worker: Worker[int] = Worker(handle, on_error=on_error)
    worker.start()
    worker.submit(1)
    assert failed.wait(5)  # only then the next: the worker keeps the newest waiting frame alone
    worker.submit(2)
    assert worker.stop(drain=True, timeout=5)
    assert errors == ["bad frame"] and done == [2]


# -- statistics ------------------------------------------------------------------------------------
def test_warn_once_warns_once_per_cause() -> None:
    logged: list[str] = []
    warn = WarnOnce(logged.append)
    for _ in range(3):
        warn("cloud: truncated data", "x")
        warn("image: unknown encoding", "y")
    assert len(logged) == 2 and warn.causes == ["cloud: truncated data", "image: unknown encoding"]


def test_latency_percentiles_cover_the_latest_window() -> None:
    window = Window(10)
    assert window.percentiles(50) is None
    for v in range(100):
        window.add(float(v))
    assert window.percentiles(50, 100) == [94.5, 99.0]


def test_rates_count_messages_per_second_over_the_window() -> None:
    clock = FakeClock()
    meter = RateMeter(window=2.0, clock=clock)
    for i in range(10):
        clock.now = i * 0.5
        meter.tick("a")
    assert meter.rates()["a"] == pytest.approx(2.5)  # 5 ticks within the last 2 s
    assert meter.totals["a"] == 10


# ---------------------------------------------------------------------- header time going back
def test_a_cloud_far_older_than_the_last_starts_a_new_timeline_instead_of_being_refused() -> None:
    """A bag played again: stamps restart 90 s back. The frame is taken and marked as a new session."""
    sync = make_sync(2, jump_back=5.0)
    for t in (100, 101):
        for k in range(2):
            sync.offer_image(k, t * S, f"old{k}@{t}")
        assert sync.offer_cloud(t * S, POINTS) is None
    assert [f.new_session for f in sync.ready()] == [False, False]
    for k in range(2):
        assert sync.offer_image(k, 10 * S, f"new{k}@10") is None  # the images restart too
    assert sync.offer_cloud(10 * S, POINTS) is None
    (frame,) = sync.ready()
    assert frame.new_session and frame.stamp_ns == 10 * S and frame.cameras == ["new0@10", "new1@10"]
    assert sync.restarts == 1
    for k in range(2):
        sync.offer_image(k, 11 * S, f"new{k}@11")
    sync.offer_cloud(11 * S, POINTS)
    (frame,) = sync.ready()
    assert not frame.new_session and frame.cameras == ["new0@11", "new1@11"]


def test_when_the_cloud_jumps_back_first_the_old_timeline_images_are_forgotten() -> None:
    sync = make_sync(1, jump_back=5.0, max_wait=10.0, camera_timeout=100.0)
    sync.offer_image(0, 100 * S, "old")
    sync.offer_cloud(100 * S, POINTS)
    sync.ready()
    assert sync.offer_cloud(10 * S, POINTS) is None  # no new image yet: the frame waits for one
    assert sync.ready() == []
    assert sync.offer_image(0, 10 * S, "new") is None  # not refused as out of order: 100 s was forgotten
    (frame,) = sync.ready()
    assert frame.cameras == ["new"] and frame.new_session


def test_a_step_back_shorter_than_jump_back_is_still_out_of_order_and_zero_refuses_every_jump() -> None:
    sync = make_sync(1, jump_back=5.0)
    sync.offer_cloud(100 * S, POINTS)
    assert sync.offer_cloud(96 * S, POINTS) == OUT_OF_ORDER
    strict = make_sync(1, jump_back=0.0)
    strict.offer_cloud(100 * S, POINTS)
    assert strict.offer_cloud(10 * S, POINTS) == OUT_OF_ORDER and strict.restarts == 0


def test_the_new_session_mark_survives_a_frame_dropped_for_missing_cameras() -> None:
    sync = make_sync(1, jump_back=5.0, min_cameras=1, max_wait=0.0, camera_timeout=100.0)
    sync.offer_image(0, 100 * S, "old")
    sync.offer_cloud(100 * S, POINTS)
    sync.ready()
    sync.offer_cloud(10 * S, POINTS)  # its image never comes: dropped ("no camera")
    assert sync.ready() == [] and sync.drops[NO_CAMERA] == 1
    sync.offer_image(0, 11 * S, "new")
    sync.offer_cloud(11 * S, POINTS)
    (frame,) = sync.ready()
    assert frame.new_session and frame.stamp_ns == 11 * S


def test_odometry_that_jumps_back_forgets_the_old_timeline_and_interpolates_the_new() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0, jump_back=5.0)
    for t in (100, 101):
        assert odom.offer(t * S, np.eye(4), "odom") is None
    for t, x in ((10, 0.0), (11, 4.0)):
        pose = np.eye(4)
        pose[0, 3] = x
        assert odom.offer(t * S, pose, "odom") is None
    assert len(odom) == 2 and odom.newest == 11 * S
    halfway = odom.pose_at(10 * S + S // 2)
    assert halfway is not None and halfway[0, 3] == pytest.approx(2.0)


def test_poses_of_the_new_timeline_that_arrive_before_the_jumped_cloud_are_kept() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0, jump_back=5.0)
    sync = Synchroniser(SyncConfig(max_wait=10.0, min_cameras=0), 0, poses=odom, clock=FakeClock())
    for t in (100, 101):
        odom.offer(t * S, np.eye(4), "odom")
        sync.offer_cloud(t * S, POINTS)
    sync.ready()
    for t in (10, 11, 12):  # odometry runs ahead of the clouds on the replayed timeline
        odom.offer(t * S, np.eye(4), "odom")
    sync.offer_cloud(10 * S, POINTS)
    assert odom.newest == 12 * S and len(odom) == 3
    (frame,) = sync.ready()
    assert frame.new_session and frame.pose is not None


def test_a_cloud_that_jumps_back_before_odometry_forgets_the_old_poses_once() -> None:
    odom = OdometryBuffer(slop=0.05, max_gap=1.0, jump_back=5.0)
    for t in (100, 101):
        odom.offer(t * S, np.eye(4), "odom")
    cloud_timeline = odom.follow_jump(10 * S, 0)  # the cloud stream jumped to 10 s first
    assert odom.newest is None and cloud_timeline == 1
    for t in (10, 11):  # in order on the new timeline: not a second jump
        assert odom.offer(t * S, np.eye(4), "odom") is None
    assert odom.follow_jump(10 * S + S // 2, 0) == 1  # a second stream's jump to the same timeline
    assert len(odom) == 2  # keeps the poses the first one already let in


def test_an_image_that_arrives_after_its_frame_went_without_it_is_counted_late() -> None:
    """The mark of a sample lost in transport and repaired seconds later (Fast DDS shared memory)."""
    from lcpr_ros.sync import LATE_IMAGE

    assert LATE_IMAGE == "image: arrived after its frame"
    clock = FakeClock()
    sync = make_sync(2, clock, max_wait=0.2)
    sync.offer_image(0, 10 * S, "a")
    sync.offer_image(1, 9 * S, "b-old")
    sync.offer_cloud(10 * S, POINTS)
    clock.now = 0.3  # camera 1's image for 10 s never came in time
    (frame,) = sync.ready()
    assert frame.cameras == ["a", None]
    sync.offer_image(1, 10 * S + 10 * MS, "b-late")  # the repair
    assert sync.late == [0, 1]
    sync.offer_image(1, 11 * S, "b-next")  # an image for the next frame is not late
    assert sync.late == [0, 1]

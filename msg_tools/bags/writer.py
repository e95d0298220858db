"""Write :class:`~msg_tools.frames.SensorFrame` streams (and single messages) to a rosbag2.

The bag is written into a temporary folder beside the target and moved into place
when the writer closes without error, so a reader never sees half a bag.

Message choices made by :meth:`BagWriter.write_frame`:

* camera with ``jpeg`` bytes -> ``sensor_msgs/CompressedImage`` holding those bytes
  unchanged (``format`` from the bytes' signature: ``jpeg`` or ``png``);
  camera with ``rgb`` -> ``sensor_msgs/Image`` ``rgb8``;
* depth -> ``sensor_msgs/Image`` ``32FC1`` (metres, 0 = unknown);
* labels -> ``sensor_msgs/Image`` ``mono16`` when every id fits 16 bits, else ``32SC1``
  holding the uint32 bits (readers view it back as uint32);
* cloud -> ``sensor_msgs/PointCloud2`` with every field of the structured array;
* pose -> ``nav_msgs/Odometry`` (``map`` -> ``base_link``) at the cloud stamp;
* camera models (when given) -> one ``sensor_msgs/CameraInfo`` per camera image, at the image stamp.

Every message is logged at its header stamp.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

from ..camera_info import model_to_camera_info
from ..compressed import compressed_from_bytes
from ..errors import BagError, BagTopicError
from ..frames import CameraImage, CameraModel, SensorFrame, Topics
from ..image import array_to_image
from ..pointcloud import array_to_pointcloud2
from ..transforms import BASE_FRAME, MAP_FRAME, pose_to_odometry, transforms_message
from ..types import Stamp, StampLike, as_stamp, stamp_to_ns, typestore

Storage = Literal["sqlite3", "mcap"]
STORAGES: dict[str, StoragePlugin] = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}

_LATCHED = Qos(
    QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
    QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False,
)


def label_image(labels: np.ndarray) -> tuple[np.ndarray, str]:
    """Label ids -> (pixels, encoding): mono16 when all ids fit 16 bits, else 32SC1 carrying uint32 bits."""
    ids = np.asarray(labels)
    if ids.ndim != 2 or ids.dtype.kind not in "ui":
        raise BagError(f"labels must be an H x W integer array, got {ids.dtype} of shape {ids.shape}")
    if ids.size and (ids.min() < 0 or ids.max() > np.iinfo(np.uint32).max):
        raise BagError(f"label ids must lie in [0, 2**32), got range [{ids.min()}, {ids.max()}]")
    if ids.size == 0 or ids.max() <= np.iinfo(np.uint16).max:
        return ids.astype(np.uint16), "mono16"
    return ids.astype(np.uint32).view(np.int32), "32SC1"


class BagWriter:
    """Context manager writing a rosbag2 (``storage="sqlite3"`` or ``"mcap"``).

    ``overwrite=True`` replaces an existing bag at ``path`` once the new one is
    complete; otherwise an existing path raises :class:`BagError`.
    """

    def __init__(self, path: str | os.PathLike[str], *, storage: Storage = "sqlite3", overwrite: bool = False) -> None:
        if storage not in STORAGES:
            raise BagError(f"storage {storage!r} is not supported; accepted: {', '.join(STORAGES)}")
        self.path = Path(path)
        self.storage = storage
        self.overwrite = overwrite
        self._tmpdir: Path | None = None
        self._writer: Writer | None = None
        self._connections: dict[str, tuple[Any, str]] = {}
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._pending_static: list[tuple[str, Any]] = []  # (topic, transforms) awaiting a stamp

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> BagWriter:
        if self._writer is not None:
            raise BagError(f"bag writer for {self.path} is already open")
        if self.path.exists() and not self.overwrite:
            raise BagError(f"{self.path} exists already; pass overwrite=True to replace it")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent))
        self._writer = Writer(self._tmpdir / self.path.name, version=Writer.VERSION_LATEST,
                              storage_plugin=STORAGES[self.storage])
        try:
            self._writer.open()
        except WriterError as err:
            self.abort()
            raise BagError(f"cannot open a {self.storage} bag at {self.path}: {err}") from err
        return self

    def close(self) -> None:
        """Finish the bag and move it to ``path``."""
        writer, tmpdir = self._require_open(), self._tmpdir
        assert tmpdir is not None
        try:
            if self._pending_static:
                self._flush_static(self._first_ns if self._first_ns is not None else 0)
            writer.close()
        except (WriterError, OSError) as err:
            self.abort()
            raise BagError(f"cannot finish the bag {self.path}: {err}") from err
        self._writer = None
        built = tmpdir / self.path.name
        if self.path.exists():
            os.replace(self.path, tmpdir / ".replaced")
        os.replace(built, self.path)
        shutil.rmtree(tmpdir, ignore_errors=True)
        self._tmpdir = None

    def abort(self) -> None:
        """Drop everything written; ``path`` is left as it was."""
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:  # noqa: BLE001 - the bag is being thrown away
                pass
            self._writer = None
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far, per topic."""
        return dict(self._counts)

    # -- single messages -----------------------------------------------------------------
    def write(self, topic: str, msg: Any, *, stamp: StampLike | None = None) -> None:
        """Serialise a rosbags message and log it at ``stamp`` (default: its header stamp)."""
        msgtype = getattr(msg, "__msgtype__", None)
        if msgtype is None:
            raise BagError(
                f"cannot write {type(msg).__name__} to {topic}: BagWriter writes rosbags messages "
                "(build them with msg_tools' converters, which default to rosbags classes)"
            )
        if stamp is not None:
            ns = as_stamp(stamp).ns
        elif hasattr(msg, "header"):
            ns = stamp_to_ns(msg.header)
        else:
            raise BagError(f"{msgtype} on {topic} has no header; pass stamp=")
        if self._pending_static and self._first_ns is None:
            self._flush_static(ns)
        self._write_raw(topic, msgtype, msg, ns)

    def _write_raw(self, topic: str, msgtype: str, msg: Any, ns: int) -> None:
        writer = self._require_open()
        connection = self._connection(topic, msgtype)
        data = typestore().serialize_cdr(msg, msgtype)
        writer.write(connection, ns, data)
        self._counts[topic] = self._counts.get(topic, 0) + 1
        self._first_ns = ns if self._first_ns is None else min(self._first_ns, ns)

    def _connection(self, topic: str, msgtype: str) -> Any:
        known = self._connections.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise BagTopicError(f"topic {topic} already carries {known[1]}; cannot also write {msgtype} to it")
            return known[0]
        qos = [_LATCHED] if msgtype == "tf2_msgs/msg/TFMessage" and topic.endswith("tf_static") else []
        connection = self._require_open().add_connection(
            topic, msgtype, typestore=typestore(), offered_qos_profiles=qos
        )
        self._connections[topic] = (connection, msgtype)
        return connection

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise BagError(f"bag writer for {self.path} is not open; use it as a context manager or call open()")
        return self._writer

    # -- typed helpers ---------------------------------------------------------------------
    def write_cloud(self, topic: str, cloud: np.ndarray, *, frame_id: str, stamp: StampLike) -> None:
        self.write(topic, array_to_pointcloud2(cloud, frame_id=frame_id, stamp=stamp))

    def write_image(self, topic: str, pixels: np.ndarray, *, encoding: str, frame_id: str, stamp: StampLike) -> None:
        self.write(topic, array_to_image(pixels, encoding=encoding, frame_id=frame_id, stamp=stamp))

    def write_encoded(self, topic: str, data: bytes, *, frame_id: str, stamp: StampLike) -> None:
        """Already encoded JPEG/PNG bytes -> CompressedImage, byte for byte."""
        self.write(topic, compressed_from_bytes(data, frame_id=frame_id, stamp=stamp))

    def write_camera_info(self, topic: str, model: CameraModel, *, stamp: StampLike) -> None:
        self.write(topic, model_to_camera_info(model, stamp=stamp))

    def write_odometry(
        self, topic: str, pose: np.ndarray, *, stamp: StampLike,
        frame_id: str = MAP_FRAME, child_frame_id: str = BASE_FRAME,
    ) -> None:
        self.write(topic, pose_to_odometry(pose, stamp=stamp, frame_id=frame_id, child_frame_id=child_frame_id))

    def write_static_transforms(
        self,
        cameras: Sequence[CameraModel],
        lidar_frame: str,
        base_T_lidar: np.ndarray,
        *,
        stamp: StampLike | None = None,
        topic: str = "/tf_static",
        base_frame: str = BASE_FRAME,
    ) -> None:
        """``base_frame`` -> each camera's frame and -> ``lidar_frame`` as one tf2_msgs/TFMessage.

        Without ``stamp`` it is stamped with the earliest stamp written so far or, when
        nothing was written yet, held back and stamped with the next message written.
        """
        transforms = [(base_frame, cam.frame_id, cam.base_T_cam) for cam in cameras]
        transforms.append((base_frame, lidar_frame, base_T_lidar))
        msg = transforms_message(transforms, stamp=Stamp(0, 0))  # validated now, stamped when written
        if stamp is not None:
            self._write_static(topic, msg, as_stamp(stamp).ns)
        elif self._first_ns is not None:
            self._write_static(topic, msg, self._first_ns)
        else:
            self._pending_static.append((topic, msg))

    def _flush_static(self, ns: int) -> None:
        pending, self._pending_static = self._pending_static, []
        for topic, msg in pending:
            self._write_static(topic, msg, ns)

    def _write_static(self, topic: str, msg: Any, ns: int) -> None:
        stamp = Stamp.from_ns(ns)
        for t in msg.transforms:
            t.header.stamp.sec, t.header.stamp.nanosec = stamp.sec, stamp.nanosec
        self._write_raw(topic, "tf2_msgs/msg/TFMessage", msg, ns)

    # -- frames ----------------------------------------------------------------------------
    def write_frame(self, frame: SensorFrame, *, topics: Topics, cameras: Sequence[CameraModel] | None = None) -> None:
        """Write one synchronised frame (see the module docstring for the message choices)."""
        if len(frame.cameras) > len(topics.cameras):
            raise BagTopicError(
                f"the frame has {len(frame.cameras)} cameras but topics name {len(topics.cameras)} camera topics"
            )
        if cameras is not None and len(cameras) != len(frame.cameras):
            raise BagTopicError(f"{len(cameras)} camera models given for a frame with {len(frame.cameras)} cameras")
        for index, image in enumerate(frame.cameras):
            if image is not None:
                self._write_camera(index, image, topics, None if cameras is None else cameras[index])
        self.write_cloud(topics.lidar, frame.cloud, frame_id=frame.lidar_frame_id, stamp=frame.stamp)
        if frame.pose is not None:
            self.write_odometry(topics.odom, frame.pose, stamp=frame.stamp)

    def _write_camera(self, index: int, image: CameraImage, topics: Topics, model: CameraModel | None) -> None:
        topic = topics.cameras[index]
        if image.jpeg is not None:
            self.write_encoded(topic, image.jpeg, frame_id=image.frame_id, stamp=image.stamp)
        else:
            assert image.rgb is not None
            self.write_image(topic, image.rgb, encoding="rgb8", frame_id=image.frame_id, stamp=image.stamp)
        if image.depth is not None:
            depth = np.asarray(image.depth)
            if depth.dtype.kind != "f":
                raise BagError(f"camera {index} depth must be float metres, got {depth.dtype}")
            self.write_image(_topic_at(topics.depth, index, "depth"), depth.astype(np.float32, copy=False),
                             encoding="32FC1", frame_id=image.frame_id, stamp=image.stamp)
        if image.labels is not None:
            pixels, encoding = label_image(image.labels)
            self.write_image(_topic_at(topics.labels, index, "labels"), pixels, encoding=encoding,
                             frame_id=image.frame_id, stamp=image.stamp)
        if model is not None and topics.camera_info:
            self.write_camera_info(_topic_at(topics.camera_info, index, "camera_info"), model, stamp=image.stamp)


def _topic_at(names: Sequence[str], index: int, what: str) -> str:
    if index >= len(names):
        raise BagTopicError(f"camera {index} has {what} but topics name only {len(names)} {what} topic(s): "
                            f"{list(names)}")
    return names[index]

"""Opening rosbag2 folders for reading, with msg_tools' errors."""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rosbags.rosbag2 import Reader, ReaderError

from ..errors import BagError, BagTopicError


@contextmanager
def open_bag(path: str | os.PathLike[str]) -> Iterator[Reader]:
    """An open rosbags ``Reader`` (sqlite3 or mcap storage, chosen by the bag's metadata)."""
    bag = Path(path)
    if not (bag / "metadata.yaml").is_file():
        raise BagError(f"{bag} is not a rosbag2 folder (no metadata.yaml); accepted: a rosbag2 directory")
    try:
        reader = Reader(bag)
        reader.open()
    except (ReaderError, OSError) as err:
        raise BagError(f"cannot open bag {bag}: {err}") from err
    try:
        yield reader
    finally:
        reader.close()


def topic_types(reader: Reader) -> dict[str, str]:
    """topic -> message type of every topic in the bag."""
    return {c.topic: c.msgtype for c in reader.connections}


def check_topic(types: dict[str, str], topic: str, accepted: tuple[str, ...], *, required: bool) -> bool:
    """True when ``topic`` is present with an accepted type; False when absent and optional."""
    msgtype = types.get(topic)
    if msgtype is None:
        if required:
            raise BagTopicError(f"topic {topic} is not in the bag; its topics are {sorted(types)}")
        return False
    if msgtype not in accepted:
        raise BagTopicError(f"topic {topic} carries {msgtype}; accepted: {', '.join(accepted)}")
    return True


def storage_of(path: str | os.PathLike[str]) -> str:
    """``"sqlite3"`` or ``"mcap"`` from the bag's data files."""
    bag = Path(path)
    if any(bag.glob("*.mcap")):
        return "mcap"
    if any(bag.glob("*.db3")):
        return "sqlite3"
    return "unknown"

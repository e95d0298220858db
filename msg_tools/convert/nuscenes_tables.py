"""The nuScenes v1.0 tables (``<root>/<version>/*.json``) a converter needs, indexed by token."""
from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import DatasetError

TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor", "log")
Record = dict[str, Any]


def _load(folder: Path, name: str) -> list[Record]:
    path = folder / f"{name}.json"
    try:
        with path.open("r", encoding="utf-8") as fh:
            rows = json.load(fh)
    except FileNotFoundError as err:
        raise DatasetError(f"nuScenes table {path} is missing; a version folder holds {', '.join(TABLES)}") from err
    except json.JSONDecodeError as err:
        raise DatasetError(f"nuScenes table {path} is not valid JSON: {err}") from err
    if not isinstance(rows, list):
        raise DatasetError(f"nuScenes table {path} holds a {type(rows).__name__}; expected a list of records")
    return rows


@dataclass
class NuScenesTables:
    """Token-indexed tables, plus keyframe sample_data grouped by sample and channel."""

    root: Path
    scenes: list[Record]
    samples: dict[str, Record]
    calibrated_sensors: dict[str, Record]
    ego_poses: dict[str, Record]
    sensors: dict[str, Record]
    logs: dict[str, Record]
    keyframes: dict[str, dict[str, Record]]  # sample token -> channel -> sample_data

    @classmethod
    def load(cls, root: str | Path, version: str) -> NuScenesTables:
        base = Path(root)
        folder = base / version
        if not folder.is_dir():
            found = sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []
            raise DatasetError(f"no nuScenes version folder {folder}; folders in {base}: {found}")
        by_token = {name: {r["token"]: r for r in _load(folder, name)} for name in TABLES if name != "scene"}
        tables = cls(
            root=base,
            scenes=_load(folder, "scene"),
            samples=by_token["sample"],
            calibrated_sensors=by_token["calibrated_sensor"],
            ego_poses=by_token["ego_pose"],
            sensors=by_token["sensor"],
            logs=by_token["log"],
            keyframes={},
        )
        for sd in by_token["sample_data"].values():
            if sd.get("is_key_frame"):
                tables.keyframes.setdefault(sd["sample_token"], {})[tables.channel_of(sd)] = sd
        return tables

    def channel_of(self, sample_data: Record) -> str:
        try:
            calibrated = self.calibrated_sensors[sample_data["calibrated_sensor_token"]]
            return str(self.sensors[calibrated["sensor_token"]]["channel"])
        except KeyError as err:
            raise DatasetError(f"sample_data {sample_data.get('token')!r} refers to a missing record {err}") from err

    def location_of(self, scene: Record) -> str:
        return str(self.logs[scene["log_token"]]["location"])

    def select(self, *, names: Sequence[str] = (), locations: Sequence[str] = ()) -> list[Record]:
        """Scenes named in ``names`` or recorded in ``locations``, ordered by their first sample's time."""
        if not names and not locations:
            raise DatasetError("choose scenes: give at least one scene name or location")
        by_name = {s["name"]: s for s in self.scenes}
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise DatasetError(f"unknown scene(s) {unknown}; this version has {_preview(sorted(by_name))}")
        known_locations = sorted({self.location_of(s) for s in self.scenes})
        bad = [loc for loc in locations if loc not in known_locations]
        if bad:
            raise DatasetError(f"unknown location(s) {bad}; accepted: {known_locations}")
        chosen = {s["token"]: s for s in self.scenes if s["name"] in names or self.location_of(s) in locations}
        return sorted(chosen.values(), key=lambda s: self.samples[s["first_sample_token"]]["timestamp"])

    def scene_samples(self, scene: Record) -> Iterator[Record]:
        """The scene's samples in time order (following ``next`` links)."""
        token = scene["first_sample_token"]
        while token:
            try:
                sample = self.samples[token]
            except KeyError as err:
                raise DatasetError(f"scene {scene['name']!r} links to missing sample {token!r}") from err
            yield sample
            token = sample.get("next", "")


def _preview(names: list[str], limit: int = 12) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} scenes)" if len(names) > limit else "")

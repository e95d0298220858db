"""The bundled trained weights: where they live, how a weights setting names them, and the operating
threshold a weights file carries.

A weights setting (``model.weights``, ``--weights``) is a file path or one of two names:
``bundled`` (the trained weights shipped with the package; what every entry point uses when told
nothing) and ``seeded`` (the seeded random initialisation, for tests and baselines only).
"""
from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path

from .errors import CheckpointError, InvalidValueError

PACKAGE = "lcpr_loop_closure"
#: Weights setting naming the bundled trained weights.
BUNDLED = "bundled"
#: Weights setting naming the seeded random initialisation (testing only).
SEEDED = "seeded"
WEIGHTS_NAMES = (BUNDLED, SEEDED)
#: ``match.max_distance`` meaning "automatic" (see :func:`effective_max_distance`).
AUTO_DISTANCE = -1.0
#: The distance used when neither the user nor the weights file names one: every candidate of the top k.
FALLBACK_MAX_DISTANCE = 1.0
#: Checkpoint entry holding the operating threshold: {"max_distance": float, "chosen_on": str}.
THRESHOLD_KEY = "operating_threshold"

BUNDLED_NAME = "lcpr_synth_narrow.pth"
#: match.max_distance for the bundled weights: their max-F1 threshold (0.701, online protocol, whitened
#: and turn-averaged descriptors) on the validation city grid seed 3 (neither a training city nor a
#: test city nor the demo's), from benchmarks/recipes/lcpr_finetune.py (step 7, the float16 file shipped) on the
#: corpus of benchmarks/recipes/lcpr_corpus.sh.
BUNDLED_MAX_DISTANCE = 0.70
#: VSeq2PC (sequence model, descriptor model) trained on synthetic KITTI-like drives whose depth is a
#: monocular depth network's (none beyond 25 m, a smooth 10 % error), from
#: benchmarks/recipes/vseq2pc_train_synth.sh (docs/vseq2pc.md).
VSEQ2PC_BUNDLED_NAMES = ("vseq2pc_synth_sequence.pth", "vseq2pc_synth_descriptor.pth")
#: The same recipe (12 stage-2 epochs) on drives with exact depth to any range: for depth that is close to
#: exact (projected LiDAR, stereo, RGB-D). Each set trails the other on the other's depth (docs/vseq2pc.md).
VSEQ2PC_EXACT_DEPTH_NAMES = ("vseq2pc_synth_exact_sequence.pth", "vseq2pc_synth_exact_descriptor.pth")
#: ``default_vseq2pc_weights(depth=...)``: which bundled VSeq2PC set suits which depth images.
VSEQ2PC_DEPTH_KINDS = {"network": VSEQ2PC_BUNDLED_NAMES, "exact": VSEQ2PC_EXACT_DEPTH_NAMES}


def weight_folders() -> list[Path]:
    """Where bundled weights are looked for, in order: a source checkout, pip's data files under
    ``sys.prefix``, and every ament prefix (a colcon install under a system ROS 2, whose share folder
    is not under ``sys.prefix``)."""
    folders = [Path(__file__).resolve().parents[1] / "weights", Path(sys.prefix) / "share" / PACKAGE / "weights"]
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    folders += [Path(prefix) / "share" / PACKAGE / "weights" for prefix in prefixes]
    return folders


def _bundled(name: str) -> str | None:
    for folder in weight_folders():
        if (folder / name).is_file():
            return str(folder / name)
    return None


def default_weights() -> str | None:
    """Path of the bundled trained LCPR checkpoint, or None when this install has none."""
    return _bundled(BUNDLED_NAME)


def default_vseq2pc_weights(*, depth: str = "network") -> tuple[str, str] | None:
    """Paths of the bundled trained VSeq2PC (sequence, descriptor) weights for ``depth`` images ("network":
    a monocular depth network's, the default; "exact"), or None when this install has none."""
    try:
        names = VSEQ2PC_DEPTH_KINDS[depth]
    except KeyError as err:
        raise InvalidValueError(f"depth {depth!r}: expected one of {', '.join(sorted(VSEQ2PC_DEPTH_KINDS))}") from err
    sequence, descriptor = (_bundled(name) for name in names)
    return (sequence, descriptor) if sequence and descriptor else None


def resolve_weights(weights: str) -> str:
    """A weights setting as a file path: ``bundled`` -> the bundled file, ``seeded`` -> "" (random), a path
    unchanged ("" stays "": the Python API's "no weights"). CheckpointError when the bundled file is missing."""
    if weights == SEEDED:
        return ""
    if weights != BUNDLED:
        return weights
    path = default_weights()
    if path is None:
        looked = ", ".join(str(f) for f in weight_folders())
        raise CheckpointError(f"model.weights={BUNDLED!r}: {BUNDLED_NAME} is not in this install (looked in {looked});"
                              f" pass a weights file, or {SEEDED!r} for random weights (testing only)")
    return path


def command_weights(weights: str, *, imagenet: str = "") -> str:
    """The weights setting of a node or command line: "" means the bundled weights there (random weights
    only when asked by name, ``seeded``), unless ImageNet blocks were asked for instead."""
    return BUNDLED if not weights and not imagenet else weights


def operating_threshold(weights: str) -> float | None:
    """The descriptor distance a weights file names as its operating threshold, or None (no file, or a
    file without one, such as the authors' released checkpoints)."""
    if not weights:
        return None
    from .torch_files import load_checkpoint  # torch: only when a file is read

    try:
        entry = load_checkpoint(weights, mmap=True)
    except CheckpointError:
        return None  # loading the network reports what is wrong with the file
    found = entry.get(THRESHOLD_KEY) if isinstance(entry, Mapping) else None
    if found is None:
        return None
    value = found.get("max_distance") if isinstance(found, Mapping) else None
    if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise CheckpointError(f"{weights!r} has {THRESHOLD_KEY}={found!r}; expected {{'max_distance': a distance "
                              ">= 0, 'chosen_on': text}}")
    return float(value)


def effective_max_distance(max_distance: float, threshold: float | None, *, verified: bool) -> float:
    """``match.max_distance`` as used. A given distance (>= 0) wins. AUTO_DISTANCE: with LiDAR verification,
    FALLBACK_MAX_DISTANCE (every top-k candidate is checked; the registration decides); without, the weights
    file's operating ``threshold`` (:func:`operating_threshold`), or FALLBACK_MAX_DISTANCE when it has none."""
    if max_distance >= 0:
        return max_distance
    return FALLBACK_MAX_DISTANCE if verified or threshold is None else threshold


def threshold_text(max_distance: float, threshold: float | None, *, verified: bool) -> str:
    """Which ``match.max_distance`` is used and why, for a log line."""
    used = effective_max_distance(max_distance, threshold, verified=verified)
    source = ("set" if max_distance >= 0 else "automatic: every top-k candidate is verified" if verified
              else "the weights file's operating threshold" if threshold is not None
              else "automatic: no threshold in the weights file")
    return f"match.max_distance {used:.3g} ({source})"


def describe_weights(weights: str) -> str:
    """What a resolved weights path is, for an entry point's first log line."""
    if not weights:
        return "seeded random weights (NOT a trained network: for tests only; descriptors mean nothing)"
    if weights == default_weights():
        return (f"the bundled weights {weights} (trained on synthetic cities; for a real vehicle pass the authors' "
                "released checkpoint: model.weights:=FILE)")
    return f"weights {weights}"


def with_operating_threshold(checkpoint: Mapping[str, object], *, max_distance: float,
                             chosen_on: str) -> dict[str, object]:
    """``checkpoint`` with its operating threshold entry (how the recipes mark the weights they ship)."""
    if not math.isfinite(max_distance) or max_distance < 0:
        raise InvalidValueError(f"max_distance={max_distance!r}; it must be a finite distance >= 0")
    return {**checkpoint, THRESHOLD_KEY: {"max_distance": float(max_distance), "chosen_on": chosen_on}}


#: VSeq2PC weight settings naming a bundled set: which depth images it suits (see VSEQ2PC_DEPTH_KINDS).
VSEQ2PC_BUNDLED = {BUNDLED: "network", f"{BUNDLED}-exact": "exact"}
VSEQ2PC_WEIGHTS_NAMES = (*VSEQ2PC_BUNDLED, SEEDED)


def resolve_vseq2pc_weights(sequence: str, descriptor: str) -> tuple[str, str] | None:
    """VSeq2PC (sequence, descriptor) settings as files, or None for the seeded random weights.

    Both name the same set (``bundled``: for a depth network's depth, ``bundled-exact``: for exact depth,
    ``seeded``) or both are files; "" counts as ``bundled``. InvalidValueError / CheckpointError otherwise."""
    sequence, descriptor = sequence or BUNDLED, descriptor or BUNDLED
    named = [s in VSEQ2PC_WEIGHTS_NAMES for s in (sequence, descriptor)]
    if any(named) and sequence != descriptor:
        raise InvalidValueError(f"model.sequence={sequence!r} and model.descriptor={descriptor!r}: give two weight "
                                f"files, or the same name in both ({', '.join(VSEQ2PC_WEIGHTS_NAMES)})")
    if sequence == SEEDED:
        return None
    if sequence in VSEQ2PC_BUNDLED:
        found = default_vseq2pc_weights(depth=VSEQ2PC_BUNDLED[sequence])
        if found is None:
            raise CheckpointError(f"model.sequence={sequence!r}: the bundled VSeq2PC weights are not in this install "
                                  f"(looked in {', '.join(str(f) for f in weight_folders())}); pass weight files")
        return found
    return sequence, descriptor


def describe_vseq2pc_weights(files: tuple[str, str] | None) -> str:
    """What :func:`resolve_vseq2pc_weights` resolved to (None: seeded), for an entry point's first log line."""
    if files is None:
        return "seeded random weights (NOT trained: for tests only; matches mean nothing)"
    for name, depth in VSEQ2PC_BUNDLED.items():
        if files == default_vseq2pc_weights(depth=depth):
            return (f"the bundled weights {files[0]}, {files[1]} ({name}: trained on synthetic drives with "
                    f"{'exact' if depth == 'exact' else 'network-like'} depth; for a real vehicle pass the "
                    "authors' released models: model.sequence:=FILE model.descriptor:=FILE)")
    return f"weights {files[0]}, {files[1]}"

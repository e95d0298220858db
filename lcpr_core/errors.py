"""Exceptions raised by lcpr_core; every message names the bad value and what is accepted."""

from lcpr_common.errors import ProjectError


class LcprError(ProjectError):
    """Base class of every error raised by lcpr_core."""


class InvalidValueError(LcprError, ValueError):
    """An argument, setting or input value outside what is accepted (the message names both)."""


class DatasetFileError(LcprError, FileNotFoundError):
    """A dataset folder lacks the files it should hold (the message names what was expected)."""


class CheckpointError(LcprError):
    """A weights file cannot be read or does not fit the model."""


class UnsafePickleError(CheckpointError):
    """A pickle names a global the restricted unpickler does not allow; nothing from it ran."""


class CacheError(LcprError):
    """A bag could not be turned into training samples."""


class InputShapeError(LcprError, ValueError):
    """A tensor or array handed to a model or preprocessing step has the wrong shape."""


class MapError(LcprError):
    """A descriptor map cannot be used, saved or loaded."""


class MapSchemaError(MapError):
    """A saved descriptor map does not match the map it is loaded into (dimension, model)."""


class PoseGraphError(LcprError):
    """A trajectory, loop constraint or option handed to the pose-graph back end cannot be used."""


class BackendError(PoseGraphError):
    """The online back end (:mod:`lcpr_core.backend`) refused an input, an option or a graph file.

    ``reason`` is a short, stable cause (counted in the back end's statistics); the message names the
    value. After a refusal the graph, and any file it was saved to, are as they were.
    """

    def __init__(self, message: str, *, reason: str = "invalid input") -> None:
        super().__init__(message)
        self.reason = reason


class VerificationError(LcprError, ValueError):
    """Geometric verification was given clouds, transforms or settings it cannot use."""


class RuntimeSetupError(LcprError):
    """An inference path (exported graph, int8 model, runtime library) cannot be built or loaded."""


class DeviceError(LcprError):
    """The device failed while describing a frame (a GPU out of memory); the frame is skipped, nothing stored."""


class PeerKeyframeError(InvalidValueError):
    """A peer keyframe record that cannot be read (truncated, not a record, inconsistent sizes)."""

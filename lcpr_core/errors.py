"""Exceptions raised by lcpr_core; every message names the bad value and what is accepted."""


class LcprError(Exception):
    """Base class of every error raised by lcpr_core."""


class CheckpointError(LcprError):
    """A weights file cannot be read or does not fit the model."""


class InputShapeError(LcprError, ValueError):
    """A tensor or array handed to a model or preprocessing step has the wrong shape."""


class MapError(LcprError):
    """A descriptor map cannot be used, saved or loaded."""


class MapSchemaError(MapError):
    """A saved descriptor map does not match the map it is loaded into (dimension, model)."""


class PoseGraphError(LcprError):
    """A trajectory, loop constraint or option handed to the pose-graph back end cannot be used."""


class VerificationError(LcprError, ValueError):
    """Geometric verification was given clouds, transforms or settings it cannot use."""


class RuntimeSetupError(LcprError):
    """An inference path (exported graph, int8 model, runtime library) cannot be built or loaded."""

"""VSeq2PC weight files: the released ones, and the ones training writes.

The authors released the descriptor model as ``{'state_dict': ...}`` (read with
``torch.load(weights_only=True)`` by :func:`lcpr_core.lcpr.checkpoint.read_state_dict`) and
the sequence model as a whole pickled module (``torch.save(model)``). Unpickling such a
file normally imports the authors' classes and runs whatever the pickle names, so it
is read here by :class:`RestrictedUnpickler` instead:

* module classes (``__main__.Net``, ``torch.nn.modules.linear.Linear``, any CapWords
  class outside the standard library) become inert stand-ins (:class:`StubObject`) that
  only record the state pickle hands them; nothing is imported;
* tensors are rebuilt by this module's own versions of torch's rebuild functions from
  the storages in the zip archive (``persistent_load``);
* ``collections.OrderedDict``, ``set``/``frozenset``, ``torch.Size`` (as a tuple) and
  torch's storage type names are allowed;
* every other global (``os.system``, ``builtins.eval``, ``subprocess.Popen``, any
  function) is refused with :class:`UnsafePickleError` before anything runs.

The stand-in tree is then walked (``_parameters``, persistent ``_buffers``,
``_modules``) into a flat state dict and checked against :class:`SequenceModel`.
Training writes both models in the released layouts, never as pickled modules.
"""
from __future__ import annotations

import _compat_pickle
import collections
import io
import os
import pickle
import sys
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..atomic import save_torch
from ..errors import CheckpointError, UnsafePickleError
from ..torch_files import check_state_dict, read_state_dict
from .models import DescriptorModel, SequenceModel

__all__ = [
    "RestrictedUnpickler", "StubObject", "UnsafePickleError", "load_descriptor_state_dict",
    "load_sequence_state_dict", "read_pickled_module_state_dict", "save_descriptor_weights",
    "save_sequence_weights",
]

_STORAGE_DTYPES: dict[str, torch.dtype] = {
    "FloatStorage": torch.float32, "DoubleStorage": torch.float64, "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16, "LongStorage": torch.int64, "IntStorage": torch.int32,
    "ShortStorage": torch.int16, "CharStorage": torch.int8, "ByteStorage": torch.uint8,
    "BoolStorage": torch.bool, "UntypedStorage": torch.uint8,
}
_STATE_KEYS = ("state_dict", "net", "model", "sequence_model")


@dataclass(frozen=True)
class StorageType:
    """Stand-in for a torch storage class named in a pickle (``torch.FloatStorage``...)."""

    name: str
    dtype: torch.dtype


@dataclass(frozen=True)
class Storage:
    """One storage read from the archive: a flat tensor of its dtype."""

    flat: torch.Tensor


class StubObject:
    """Inert stand-in for a class named in a pickle: it records its arguments and state, nothing else."""

    stub_module: str = ""
    stub_name: str = ""

    def __new__(cls, *args: Any, **kwargs: Any) -> StubObject:
        return super().__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.__dict__["stub_args"] = args

    def __setstate__(self, state: Any) -> None:
        slots = None
        if isinstance(state, tuple) and len(state) == 2:
            state, slots = state
        if isinstance(state, Mapping):
            self.__dict__.update(state)
        if isinstance(slots, Mapping):
            self.__dict__.update(slots)

    def __reduce__(self) -> Any:  # never re-pickle a stand-in as if it were the real class
        raise TypeError(f"{self.stub_path} is a stand-in from a restricted unpickler and cannot be pickled")

    @property
    def stub_path(self) -> str:
        return f"{self.stub_module}.{self.stub_name}"

    @property
    def state(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "stub_args"}

    def __repr__(self) -> str:
        return f"<stand-in for {self.stub_path}>"


@dataclass(frozen=True)
class TypeMarker:
    """Stand-in for a tensor type named as an argument (``torch.Tensor``); calling it is refused."""

    name: str

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise UnsafePickleError(f"the pickle calls {self.name}; only tensor rebuilding is allowed")


def _stub_class(module: str, name: str) -> type[StubObject]:
    return type(name, (StubObject,), {"stub_module": module, "stub_name": name, "__module__": __name__})


# ---------------------------------------------------------------------- tensor rebuilding (own versions)
def _rebuild_tensor(storage: Any, offset: Any, size: Any, stride: Any, requires_grad: Any = False,
                    hooks: Any = None, metadata: Any = None) -> torch.Tensor:
    """torch._utils._rebuild_tensor_v2's arguments -> a plain tensor (a copy of the view)."""
    if not isinstance(storage, Storage):
        raise CheckpointError(f"a tensor refers to {type(storage).__name__}, not to a storage of the archive")
    shape, steps = _int_tuple(size, "size"), _int_tuple(stride, "stride")
    if not isinstance(offset, int) or offset < 0 or len(shape) != len(steps):
        raise CheckpointError(f"tensor with offset {offset!r}, size {shape}, stride {steps}: inconsistent")
    numel = storage.flat.numel()
    if any(s == 0 for s in shape):
        return torch.empty(shape, dtype=storage.flat.dtype)
    last = offset + sum((s - 1) * st for s, st in zip(shape, steps, strict=True))
    if any(st < 0 for st in steps) or last >= numel:
        raise CheckpointError(f"tensor of size {shape}, stride {steps}, offset {offset} reaches element {last} "
                              f"of a storage of {numel}")
    return torch.as_strided(storage.flat, shape, steps, offset).clone()


def _rebuild_parameter(data: Any, requires_grad: Any = False, hooks: Any = None, *state: Any) -> torch.Tensor:
    if not isinstance(data, torch.Tensor):
        raise CheckpointError(f"a parameter wraps {type(data).__name__}, not a tensor")
    return data


def _rebuild_from_type(func: Any, new_type: Any, args: Any, state: Any = None) -> torch.Tensor:
    if func not in (_rebuild_tensor, _rebuild_parameter):
        raise UnsafePickleError(f"_rebuild_from_type_v2 asks to call {func!r}; only tensor rebuilding is allowed")
    return func(*args)


def _int_tuple(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, (tuple, list)) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise CheckpointError(f"tensor {what} {value!r} is not a tuple of integers")
    return tuple(value)


_ALLOWED: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    ("torch._tensor", "_rebuild_from_type_v2"): _rebuild_from_type,
    ("torch.nn.parameter", "Parameter"): _rebuild_parameter,
    ("torch", "Tensor"): TypeMarker("torch.Tensor"),  # only an argument of _rebuild_from_type_v2
    ("torch", "Size"): tuple,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
}
ACCEPTED_GLOBALS = (
    "torch._utils._rebuild_tensor_v2 / _rebuild_parameter(_with_state), torch._tensor._rebuild_from_type_v2, "
    "torch.<Type>Storage, torch.Size, collections.OrderedDict, builtins.set/frozenset, and classes "
    "(CapWords names outside the standard library, which become inert stand-ins)"
)
_STDLIB = frozenset(getattr(sys, "stdlib_module_names", ())) | {"builtins"}


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickles torch's ``data.pkl`` without importing or calling anything it names (see the module doc)."""

    def __init__(self, file: io.BufferedIOBase, *, load_storage: Callable[[StorageType, str, int], Storage]) -> None:
        super().__init__(file)
        self._load_storage = load_storage
        self._stubs: dict[tuple[str, str], type[StubObject]] = {}
        self.stubbed: set[str] = set()

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _compat_pickle.NAME_MAPPING:  # Python 2 names of protocol-2 pickles
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        allowed = _ALLOWED.get((module, name))
        if allowed is not None:
            return allowed
        if module == "torch" and name in _STORAGE_DTYPES:
            return StorageType(name, _STORAGE_DTYPES[name])
        top = module.split(".")[0]
        is_class_name = name.isidentifier() and name[:1].isupper() and "." not in name
        torch_class = module.startswith("torch.nn.modules.") or module.startswith("torch.nn.parallel.")
        if is_class_name and (module == "__main__" or torch_class or (top not in _STDLIB and top != "torch")):
            key = (module, name)
            if key not in self._stubs:
                self._stubs[key] = _stub_class(module, name)
                self.stubbed.add(f"{module}.{name}")
            return self._stubs[key]
        raise UnsafePickleError(f"refused global {module}.{name}: the file asks to call or import it, and this "
                                f"loader never runs code from a weights file; accepted: {ACCEPTED_GLOBALS}")

    def persistent_load(self, pid: Any) -> Storage:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise CheckpointError(f"persistent id {pid!r} is not ('storage', type, key, location, numel)")
        _, storage_type, key, _location, numel = pid
        if not isinstance(storage_type, StorageType):
            raise UnsafePickleError(f"persistent id names storage type {storage_type!r}; accepted: torch.<Type>Storage")
        if not isinstance(key, str) or not isinstance(numel, int) or numel < 0:
            raise CheckpointError(f"persistent id {pid!r} has a bad key or element count")
        return self._load_storage(storage_type, key, numel)


def _unpickle_zip(path: Path) -> tuple[Any, set[str]]:
    """The object in a torch.save zip archive, unpickled with :class:`RestrictedUnpickler`."""
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"{str(path)!r} is not a torch.save zip archive (PyTorch >= 1.6); the legacy format "
                              "is not supported")
    with zipfile.ZipFile(path) as archive:
        pickles = [n for n in archive.namelist() if n == "data.pkl" or n.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise CheckpointError(f"{str(path)!r} holds {len(pickles)} data.pkl entries; a torch.save archive has one")
        prefix = pickles[0][: -len("data.pkl")]
        order_name = f"{prefix}byteorder"
        if order_name in archive.namelist():
            order = archive.read(order_name).decode(errors="replace").strip()
            if order != sys.byteorder:
                raise CheckpointError(f"{str(path)!r} was written {order}-endian; this machine is {sys.byteorder}")
        cache: dict[str, Storage] = {}

        def load_storage(kind: StorageType, key: str, numel: int) -> Storage:
            if key in cache:
                return cache[key]
            entry = f"{prefix}data/{key}"
            try:
                raw = archive.read(entry)
            except KeyError as err:
                raise CheckpointError(f"{str(path)!r} lacks storage {entry!r}") from err
            size = torch.empty((), dtype=kind.dtype).element_size()
            if kind.name == "UntypedStorage":
                numel = len(raw)
            if len(raw) < numel * size:
                raise CheckpointError(f"storage {entry!r} holds {len(raw)} bytes; {numel} x {kind.name} need "
                                      f"{numel * size}")
            flat = torch.frombuffer(bytearray(raw[: numel * size]), dtype=kind.dtype) if numel else \
                torch.empty(0, dtype=kind.dtype)
            cache[key] = Storage(flat)
            return cache[key]

        unpickler = RestrictedUnpickler(io.BytesIO(archive.read(pickles[0])), load_storage=load_storage)
        try:
            obj = unpickler.load()
        except (CheckpointError, UnsafePickleError):
            raise
        except Exception as err:  # noqa: BLE001 - damaged pickles raise many kinds
            raise CheckpointError(f"{str(path)!r} cannot be unpickled: {type(err).__name__}: {err}") from err
    return obj, unpickler.stubbed


def _flatten(node: StubObject, prefix: str, out: dict[str, torch.Tensor], depth: int = 0) -> None:
    if depth > 64:
        raise CheckpointError("module tree deeper than 64 levels; refusing a cyclic or hostile structure")
    state = node.state
    for field in ("_parameters", "_buffers", "_modules"):
        if not isinstance(state.get(field, {}), Mapping):
            raise CheckpointError(f"{node.stub_path} at {prefix or '<root>'!r}: {field} is not a mapping; "
                                  "not a pickled torch module")
    skip = state.get("_non_persistent_buffers_set") or set()
    for field in ("_parameters", "_buffers"):
        for name, value in state.get(field, {}).items():
            if value is None or (field == "_buffers" and name in skip):
                continue
            if not isinstance(value, torch.Tensor):
                raise CheckpointError(f"{prefix}{name} is a {type(value).__name__}, not a tensor")
            out[f"{prefix}{name}"] = value
    for name, child in state.get("_modules", {}).items():
        if child is None:
            continue
        if not isinstance(child, StubObject):
            raise CheckpointError(f"submodule {prefix}{name} is a {type(child).__name__}, not a module")
        _flatten(child, f"{prefix}{name}.", out, depth + 1)


def _state_from(obj: Any, where: str) -> dict[str, torch.Tensor]:
    if isinstance(obj, StubObject):
        if "_modules" not in obj.state and "_parameters" not in obj.state:
            raise CheckpointError(f"{where} holds a {obj.stub_path} without module state; not a pickled torch module")
        out: dict[str, torch.Tensor] = {}
        _flatten(obj, "", out)
        return out
    if isinstance(obj, Mapping):
        if obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
            return dict(obj)
        for key in _STATE_KEYS:
            if key in obj:
                return _state_from(obj[key], where)
    raise CheckpointError(f"{where} holds no module or state dict: found {type(obj).__name__}; expected a pickled "
                          f"module, a dict of tensors, or one under {', '.join(map(repr, _STATE_KEYS))}")


def read_pickled_module_state_dict(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """The flat state dict of a ``torch.save(module)`` file (or of a saved state dict), run no code.

    A DataParallel ``module.`` prefix is removed. Raises :class:`UnsafePickleError` when
    the pickle names a global outside the allowed set, CheckpointError when the file is
    not a readable torch.save archive.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"weights file {str(path)!r} does not exist")
    obj, _ = _unpickle_zip(path)
    state = _state_from(obj, repr(str(path)))
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    return state


def load_sequence_state_dict(path: str | os.PathLike[str], *, model: SequenceModel | None = None
                             ) -> dict[str, torch.Tensor]:
    """The sequence model's weights from a released pickled module or a state dict file, checked against
    ``model``'s (default :class:`SequenceModel`) keys and shapes."""
    state = read_pickled_module_state_dict(path)
    check_state_dict(model if model is not None else SequenceModel(), state, source=f"weights file {str(path)!r}")
    return state


def load_descriptor_state_dict(path: str | os.PathLike[str], *, model: DescriptorModel | None = None
                               ) -> dict[str, torch.Tensor]:
    """The descriptor model's weights from ``{'state_dict': ...}`` (released) or a plain state dict, checked."""
    state = read_state_dict(path)
    check_state_dict(model if model is not None else DescriptorModel(), state, source=f"weights file {str(path)!r}")
    return state


def save_sequence_weights(model: nn.Module, path: str | os.PathLike[str]) -> None:
    """Write the sequence model as a plain state dict (atomically)."""
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    save_torch(state, path)


def save_descriptor_weights(model: nn.Module, path: str | os.PathLike[str]) -> None:
    """Write the descriptor model as ``{'state_dict': ...}``, the released layout (atomically)."""
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    save_torch({"state_dict": state}, path)

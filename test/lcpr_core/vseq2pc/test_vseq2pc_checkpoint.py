"""Released VSeq2PC weight files load without running code from them; training's files load back."""
from __future__ import annotations

import builtins
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from lcpr_core import CheckpointError, DescriptorModel, SequenceModel
from lcpr_core.vseq2pc.checkpoint import (
    UnsafePickleError,
    load_descriptor_state_dict,
    load_sequence_state_dict,
    read_pickled_module_state_dict,
    save_descriptor_weights,
    save_sequence_weights,
)


def seeded_sequence_model(seed: int = 3) -> SequenceModel:
    torch.manual_seed(seed)
    return SequenceModel()


def assert_same_tensors(loaded: dict[str, torch.Tensor], model: nn.Module) -> None:
    own = model.state_dict()
    assert set(loaded) == set(own)
    for key, value in own.items():
        assert loaded[key].dtype == value.dtype and torch.equal(loaded[key], value), key


class AuthorsSequenceNet(SequenceModel):
    """Stands for the authors' own class: pickled under this test module's name, or as __main__'s."""


class Shell(nn.Module):
    """A wrapper like DataParallel: the weights sit under ``module.``."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.module = inner


class RunsShell:
    """A pickle payload that would run a shell command when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return os.system, (f"touch {self.marker}",)


class Evaluates:
    """A pickle payload that would call builtins.eval when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return builtins.eval, (f"open({str(self.marker)!r}, 'w').close()",)


class Prints:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return builtins.print, ("pwned",)


def test_a_whole_pickled_sequence_module_converts_to_the_same_state_dict(tmp_path: Path) -> None:
    model = seeded_sequence_model()
    torch.save(model, tmp_path / "seq.pth")
    assert_same_tensors(load_sequence_state_dict(tmp_path / "seq.pth"), model)


def test_a_module_class_from_the_saving_script_is_not_needed_to_load(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    main = sys.modules["__main__"]
    cls = type("SeqNet", (SequenceModel,), {"__module__": "__main__", "__qualname__": "SeqNet"})
    monkeypatch.setattr(main, "SeqNet", cls, raising=False)
    torch.manual_seed(5)
    model = cls()
    torch.save(model, tmp_path / "main.pth")
    monkeypatch.delattr(main, "SeqNet")  # as in a new process: the authors' script is not importable
    assert_same_tensors(load_sequence_state_dict(tmp_path / "main.pth"), model)


def test_a_class_defined_in_another_module_is_stood_in_for_not_imported(tmp_path: Path) -> None:
    torch.manual_seed(6)
    model = AuthorsSequenceNet()
    torch.save(model, tmp_path / "authors.pth")
    sys.modules.pop("not_imported_marker", None)
    assert_same_tensors(read_pickled_module_state_dict(tmp_path / "authors.pth"), model)


def test_a_wrapped_module_loses_its_module_prefix_and_half_precision_is_kept(tmp_path: Path) -> None:
    model = seeded_sequence_model()
    torch.save(Shell(model), tmp_path / "wrapped.pth")
    assert_same_tensors(load_sequence_state_dict(tmp_path / "wrapped.pth"), model)
    torch.save(model.half(), tmp_path / "half.pth")
    assert read_pickled_module_state_dict(tmp_path / "half.pth")["decoder.head.weight"].dtype == torch.float16


def test_a_plain_state_dict_file_loads_through_the_same_path(tmp_path: Path) -> None:
    model = seeded_sequence_model()
    torch.save(model.state_dict(), tmp_path / "sd.pth")
    assert_same_tensors(load_sequence_state_dict(tmp_path / "sd.pth"), model)


@pytest.mark.parametrize("payload", ["os.system", "builtins.eval"])
def test_a_pickle_that_would_run_code_is_refused_and_nothing_runs(tmp_path: Path, payload: str) -> None:
    marker = tmp_path / "ran"
    model = seeded_sequence_model()
    # hidden in the module's dict; torch types Module.__setattr__ for tensors and modules, any value is stored
    model.extra = RunsShell(marker) if payload == "os.system" else Evaluates(marker)  # type: ignore[assignment]
    torch.save(model, tmp_path / "evil.pth")
    with pytest.raises(UnsafePickleError, match=r"refused global .*(system|eval)"):
        load_sequence_state_dict(tmp_path / "evil.pth")
    assert not marker.exists()


def test_a_top_level_malicious_object_is_refused_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    torch.save({"state_dict": Prints()}, tmp_path / "print.pth")
    with pytest.raises(UnsafePickleError, match="builtins.print"):
        read_pickled_module_state_dict(tmp_path / "print.pth")
    assert "pwned" not in capsys.readouterr().out


def test_files_that_are_not_torch_archives_or_do_not_fit_name_the_problem(tmp_path: Path) -> None:
    (tmp_path / "junk.pth").write_bytes(b"not a zip")
    with pytest.raises(CheckpointError, match="not a torch.save zip archive"):
        read_pickled_module_state_dict(tmp_path / "junk.pth")
    with pytest.raises(CheckpointError, match="does not exist"):
        read_pickled_module_state_dict(tmp_path / "missing.pth")
    torch.save(nn.Linear(3, 2), tmp_path / "linear.pth")
    with pytest.raises(CheckpointError, match=r"missing.*unexpected: weight, bias"):
        load_sequence_state_dict(tmp_path / "linear.pth")


def test_training_writes_the_released_layouts_that_load_with_weights_only(tmp_path: Path) -> None:
    seq, desc = seeded_sequence_model(), DescriptorModel()
    save_sequence_weights(seq, tmp_path / "seq.pth")
    save_descriptor_weights(desc, tmp_path / "desc.pth")
    raw = torch.load(tmp_path / "desc.pth", weights_only=True)
    assert list(raw) == ["state_dict"]
    assert_same_tensors(torch.load(tmp_path / "seq.pth", weights_only=True), seq)
    assert_same_tensors(load_descriptor_state_dict(tmp_path / "desc.pth"), desc)
    assert_same_tensors(load_sequence_state_dict(tmp_path / "seq.pth"), seq)
    assert np.isfinite(raw["state_dict"]["linear.0.weight"].numpy()).all()

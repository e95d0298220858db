"""Inference paths: the exported graph, its cache, auto's choice and the int8 refusal."""
from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcpr_core import Describer, ModelConfig
from lcpr_core.errors import RuntimeSetupError
from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
from lcpr_core.lcpr.runtime import EXACT_COSINE, graph_key, onnx_path
from lcpr_core.lcpr.runtime.choose import cosine, probe_inputs

NARROW: dict[str, Any] = dict(width=0.25, image_size=(64, 192), range_size=(16, 264), threads=2)


def narrow_weights(folder: Path, seed: int = 0) -> Path:
    torch.manual_seed(seed)
    from lcpr_core import LCPR

    model = LCPR(width=0.25, image_size=(64, 192), range_size=(16, 264))
    path = folder / f"narrow{seed}.pth"
    torch.save({"state_dict": model.state_dict(),
                "config": {"width": 0.25, "image_size": [64, 192], "range_size": [16, 264]}}, path)
    return path


def test_the_exported_graph_reproduces_the_released_code_to_1e_5(shared: Path, detweights, tmp_path: Path) -> None:
    keys = json.loads((shared / "reference" / "lcpr" / "keys.json").read_text())
    expected = np.load(shared / "reference" / "lcpr" / "expected_seed0.npz")
    weights = tmp_path / "released.pth"
    torch.save(detweights.det_state_dict(keys, 0), weights)
    describer = Describer(ModelConfig(weights=str(weights), precision="onnx", threads=2))
    assert describer.path == "onnx"
    batch = expected["descriptor"].shape[0]
    images, ranges = detweights.det_camera_input(batch, 0), detweights.det_range_input(batch, 0)
    np.testing.assert_allclose(describer.describe_tensors(images, ranges), expected["descriptor"], atol=1e-5, rtol=0)
    assert onnx_path(describer.config).parent == tmp_path  # cached next to the weights


def test_the_exported_graph_agrees_with_torch_on_a_real_frame(nuscenes_sample: Path, tmp_path: Path) -> None:
    images, points = find_nuscenes_keyframe(nuscenes_sample).read()
    weights = str(narrow_weights(tmp_path))
    exact = Describer(ModelConfig(weights=weights, precision="fp32", threads=2))
    onnx = Describer(ModelConfig(weights=weights, precision="onnx", threads=2))
    a, b = exact.describe(images, points), onnx.describe(images, points)
    assert cosine(a[None], b[None]) >= EXACT_COSINE


def test_a_changed_checkpoint_gets_a_graph_of_its_own(tmp_path: Path) -> None:
    first = narrow_weights(tmp_path, seed=0)
    config = ModelConfig(weights=str(first), precision="onnx", **NARROW)
    key = graph_key(config)
    Describer(config)
    assert onnx_path(config).is_file() and key in onnx_path(config).name
    first.write_bytes(narrow_weights(tmp_path, seed=1).read_bytes())  # same name, new weights
    assert graph_key(config) != key and not onnx_path(config).is_file()
    describer = Describer(config)  # exports again: its descriptors are the new weights'
    assert describer.model is not None
    images, ranges = probe_inputs(describer.model)
    with torch.inference_mode():
        expected = describer.model(images, ranges).numpy()
    assert cosine(describer.describe_tensors(images, ranges), expected) >= EXACT_COSINE


def test_a_graph_that_does_not_match_its_weights_is_refused_with_its_name(tmp_path: Path) -> None:
    config = ModelConfig(weights=str(narrow_weights(tmp_path, seed=0)), precision="onnx", **NARROW)
    Describer(config)
    other = ModelConfig(weights=str(narrow_weights(tmp_path, seed=1)), precision="onnx", **NARROW)
    Describer(other)
    onnx_path(config).write_bytes(onnx_path(other).read_bytes())  # a stale or swapped file under the name
    with pytest.raises(RuntimeSetupError, match=r"cosine .* delete it"):
        Describer(config)


def test_auto_keeps_the_fastest_exact_path_and_logs_the_cpu(tmp_path: Path, caplog) -> None:
    config = ModelConfig(weights=str(narrow_weights(tmp_path, seed=2)), precision="auto", **NARROW)
    with caplog.at_level(logging.INFO, logger="lcpr_core.lcpr.runtime.choose"):
        describer = Describer(config)
    choice = describer.choice
    assert set(choice.ms) | set(choice.failed) == {"fp32", "bf16", "onnx"}
    exact = [n for n in choice.ms if choice.cosines[n] >= EXACT_COSINE]
    assert describer.path == min(exact, key=choice.ms.__getitem__)
    assert "precision auto chose" in caplog.text and "threads" in caplog.text


def test_int8_without_its_graph_is_refused_naming_the_command_that_makes_it(tmp_path: Path) -> None:
    weights = narrow_weights(tmp_path)
    with pytest.raises(RuntimeSetupError, match=rf"lcpr_quantize --weights {weights}"):
        Describer(ModelConfig(weights=str(weights), precision="int8", **NARROW))


def test_an_unknown_precision_names_the_accepted_ones() -> None:
    with pytest.raises(ValueError, match="accepted: fp32, tf32, bf16, onnx, int8, auto"):
        ModelConfig(precision="fp16")


def test_lcpr_quantize_writes_the_int8_graph_the_int8_path_then_loads(tmp_path: Path, capsys, caplog) -> None:
    from lcpr_offline.lcpr_quantize import main as lcpr_quantize

    weights = narrow_weights(tmp_path, seed=3)
    assert lcpr_quantize(["--weights", str(weights), "--frames", "3", "--no-progress", "--threads", "2"]) == 0
    config = ModelConfig(weights=str(weights), precision="int8", **NARROW)
    assert onnx_path(config, "int8").parent == tmp_path and "int8 graph" in capsys.readouterr().out
    with caplog.at_level(logging.INFO, logger="lcpr_core.lcpr.runtime.choose"):
        describer = Describer(config)  # model.runtime auto: both runtimes timed, the faster kept
    assert describer.path == "int8" and describer.runtime in ("onnxruntime", "openvino")
    timed = next(r.getMessage() for r in caplog.records if "int8 runs in" in r.getMessage())
    assert "onnxruntime" in timed and "openvino" in timed and " ms" in timed
    assert describer.model is not None
    images, ranges = probe_inputs(describer.model)
    with torch.inference_mode():
        expected = describer.model(images, ranges).numpy()
    assert 0.95 <= cosine(describer.describe_tensors(images, ranges), expected) < 1.0 - 1e-9  # close, not exact
    for runtime in ("onnxruntime", "openvino"):  # the same int8 graph in either runtime: close to each other
        pinned = Describer(dataclasses.replace(config, runtime=runtime), model=describer.model)
        assert pinned.runtime == runtime
        assert cosine(pinned.describe_tensors(images, ranges), describer.describe_tensors(images, ranges)) >= 0.999


def test_int8_falls_back_to_onnx_runtime_when_openvino_cannot_compile_the_graph(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    from lcpr_core.errors import RuntimeSetupError
    from lcpr_core.lcpr.runtime import choose
    from lcpr_offline.lcpr_quantize import main as lcpr_quantize

    def refuse(path: object, **_: object) -> None:
        raise RuntimeSetupError(f"OpenVINO cannot load {str(path)!r}: a transformation failed")

    weights = narrow_weights(tmp_path, seed=5)
    assert lcpr_quantize(["--weights", str(weights), "--frames", "2", "--no-progress", "--threads", "2"]) == 0
    monkeypatch.setattr(choose, "OpenVinoBackend", refuse)
    with caplog.at_level(logging.INFO, logger="lcpr_core.lcpr.runtime.choose"):
        describer = Describer(ModelConfig(weights=str(weights), precision="int8", **NARROW))
    assert (describer.path, describer.runtime) == ("int8", "onnxruntime")
    assert any("openvino not measured" in r.getMessage() and "int8-" in r.getMessage() for r in caplog.records)
    with pytest.raises(RuntimeSetupError, match="OpenVINO cannot load"):  # pinned, it is an error
        Describer(ModelConfig(weights=str(weights), precision="int8", runtime="openvino", **NARROW))


def test_openvino_runs_the_exported_graph_exactly(tmp_path: Path) -> None:
    weights = str(narrow_weights(tmp_path, seed=4))
    exact = Describer(ModelConfig(weights=weights, precision="fp32", **NARROW))
    assert exact.model is not None
    ov = Describer(ModelConfig(weights=weights, precision="onnx", runtime="openvino", **NARROW), model=exact.model)
    assert (ov.path, ov.runtime) == ("onnx", "openvino")
    images, ranges = probe_inputs(exact.model, batch=2)
    assert cosine(ov.describe_tensors(images, ranges), exact.describe_tensors(images, ranges)) >= EXACT_COSINE


def test_an_unknown_runtime_names_the_accepted_ones() -> None:
    with pytest.raises(ValueError, match="runtime='tensorrt'; accepted: auto, onnxruntime, openvino"):
        ModelConfig(runtime="tensorrt")


def test_lcpr_quantize_refuses_to_calibrate_on_the_held_out_test_city(tmp_path: Path, capsys) -> None:
    from lcpr_offline.lcpr_quantize import main as lcpr_quantize

    weights = narrow_weights(tmp_path, seed=3)
    assert lcpr_quantize(["--weights", str(weights), "--calibration-seed", "7", "--no-progress"]) == 1
    assert "held-out test city" in capsys.readouterr().err


def test_the_heap_threshold_is_fixed_once_per_process_and_a_users_own_setting_is_kept(monkeypatch) -> None:
    from lcpr_core.lcpr.runtime import heap

    monkeypatch.setattr(heap, "_done", None)
    kept = heap.fix_mmap_threshold(environ={"MALLOC_MMAP_THRESHOLD_": "65536"})
    assert kept == "left to MALLOC_MMAP_THRESHOLD_=65536"
    assert heap.fix_mmap_threshold(environ={}) == kept  # decided once per process
    monkeypatch.setattr(heap, "_done", None)
    done = heap.fix_mmap_threshold(environ={})
    assert done in (f"fixed at {heap.MMAP_THRESHOLD} bytes", "not glibc")
    with pytest.raises(RuntimeSetupError, match="mmap threshold 0"):
        heap.fix_mmap_threshold(0)


def test_the_onnx_path_fixes_the_heap_threshold_when_it_starts(tmp_path: Path, monkeypatch) -> None:
    from lcpr_core.lcpr.runtime import heap

    monkeypatch.setattr(heap, "_done", None)
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    Describer(ModelConfig(weights=str(narrow_weights(tmp_path)), precision="onnx", **NARROW))
    assert heap._done in (f"fixed at {heap.MMAP_THRESHOLD} bytes", "not glibc")

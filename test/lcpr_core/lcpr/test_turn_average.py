"""Turn averaging: the six turned inputs, their average, its checkpoint entry and the describer applying it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lcpr_core.errors import CheckpointError, InputShapeError, InvalidValueError
from lcpr_core.lcpr.checkpoint import save_checkpoint
from lcpr_core.lcpr.describer import Describer, ModelConfig, build_model
from lcpr_core.lcpr.preprocess.camera import cameras_tensor
from lcpr_core.lcpr.preprocess.turn import turn_frame, turn_inputs
from lcpr_core.lcpr.runtime import graph_key, onnx_path
from lcpr_core.lcpr.training import export_weights
from lcpr_core.lcpr.training.config import InputConfig
from lcpr_core.lcpr.training.recipe_rules import adopt_turn_average
from lcpr_core.lcpr.turn_average import (
    ENTRY,
    TURNS,
    TurnedNetwork,
    average_turns,
    read_turn_average,
    turned_batch,
    write_turn_average,
)
from lcpr_core.lcpr.whitening import fit_whitening, write_whitened

RIG = InputConfig(num_cameras=6, image_size=(32, 64), range_size=(8, 72), width=0.125)


def write_net(path: Path, inputs: InputConfig = RIG) -> Path:
    model = build_model(ModelConfig(seed=3, num_cameras=inputs.num_cameras, image_size=inputs.image_size,
                                    range_size=inputs.range_size, width=inputs.width))
    save_checkpoint(model, path, extra={"config": inputs.model_entry()})
    return path


def inputs(batch: int = 2, cameras: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, cameras, 3, 32, 64, generator=g), torch.rand(batch, 1, 8, 72, generator=g) * 50


def unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_turned_inputs_roll_the_cameras_as_a_raw_frame_turned_by_the_same_slots():
    images = [np.full((8, 16, 3), 40 * i, np.uint8) for i in range(6)]
    batch = cameras_tensor(images, size=(32, 64)).unsqueeze(0)
    ranges = torch.zeros(1, 1, 8, 72)
    for k in range(TURNS):
        turned_images, _ = turn_frame(images, np.zeros((1, 3)), k)
        rolled, _ = turn_inputs(batch, ranges, k)
        assert torch.equal(rolled[0], cameras_tensor(turned_images, size=(32, 64)))


def test_the_turned_batch_is_turn_major_and_needs_the_six_camera_rig():
    images, ranges = inputs(batch=2)
    all_images, all_ranges = turned_batch(images, ranges)
    assert all_images.shape == (12, 6, 3, 32, 64) and all_ranges.shape == (12, 1, 8, 72)
    assert torch.equal(all_images[:2], images) and torch.equal(all_images[2:4], torch.roll(images, 1, dims=1))
    assert torch.equal(all_ranges[2:4], torch.roll(ranges, 11, dims=-1))  # 55 deg of 72 columns
    with pytest.raises(InputShapeError, match="got 4 cameras"):
        turned_batch(*inputs(cameras=4))


def test_averaging_gives_unit_descriptors_and_refuses_a_batch_that_is_not_six_turns():
    x = unit(np.random.default_rng(0).normal(size=(12, 8)))
    out = average_turns(x, 2)
    assert out.shape == (2, 8) and np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    assert np.allclose(out[1], unit(x[1::2].mean(axis=0)), atol=1e-6)
    with pytest.raises(InputShapeError, match="expected 12 x D"):
        average_turns(x[:10], 2)


def test_the_describer_averages_each_turn_after_whitening_when_the_file_asks(tmp_path):
    net = write_net(tmp_path / "net.pth")
    plain = Describer(ModelConfig(weights=str(net), precision="fp32"))
    images, ranges = inputs()
    w = fit_whitening(np.random.default_rng(1).normal(size=(400, 256)), dims=32)
    whitened = tmp_path / "whitened.pth"
    write_whitened(net, whitened, w)
    target = tmp_path / "turned.pth"
    write_turn_average(whitened, target, on=True)
    turned = Describer(ModelConfig(weights=str(target), precision="fp32"))
    assert turned.turn_average and turned.whitening is not None and not plain.turn_average
    each = np.stack([w.apply(plain.describe_tensors(*turn_inputs(images, ranges, k))) for k in range(TURNS)])
    assert np.allclose(turned.describe_tensors(images, ranges), unit(each.mean(axis=0)), atol=1e-5)
    off = Describer(ModelConfig(weights=str(target), precision="fp32", turn_average=False))
    assert not off.turn_average and np.allclose(off.describe_tensors(images, ranges), each[0], atol=1e-6)
    assert len({plain.weights_id, off.weights_id, turned.weights_id}) == 3  # maps tell the spaces apart


def test_the_turned_network_runs_the_camera_stem_once_per_frame_and_matches_the_batch_of_six_turns():
    model = build_model(ModelConfig(seed=3, num_cameras=6, image_size=(32, 64), range_size=(8, 72), width=0.125))
    images, ranges = inputs(batch=2)
    seen: list[int] = []
    hook = model.conv1_i.register_forward_hook(lambda module, args, out: seen.append(args[0].shape[0]))
    with torch.inference_mode():
        full = model(*turned_batch(images, ranges)).numpy()  # 12 x 256, turn-major
        shared = TurnedNetwork(model)(images, ranges).numpy()
    hook.remove()
    assert seen == [TURNS * 2 * 6, 2 * 6]  # the stem saw 72 images for the batch, 12 for the turned network
    assert shared.shape == full.shape == (TURNS * 2, 256)
    np.testing.assert_allclose(shared, full, atol=1e-6, rtol=0)
    with pytest.raises(InputShapeError, match="expected B x 6 x 3 x 32 x 64"):
        TurnedNetwork(model)(images[:, :4], ranges)


def test_the_exported_turned_graph_has_a_key_of_its_own_and_agrees_with_torch(tmp_path):
    target = tmp_path / "turned.pth"
    write_turn_average(write_net(tmp_path / "net.pth"), target, on=True)
    exact = Describer(ModelConfig(weights=str(target), precision="fp32"))
    graph = Describer(ModelConfig(weights=str(target), precision="onnx"))
    assert exact.turns_in_network and graph.turns_in_network and graph.runtime == "onnxruntime"
    config = graph.config
    all_turns = tuple(range(TURNS))
    assert graph_key(config, turns=all_turns) != graph_key(config) and onnx_path(config, turns=all_turns).is_file()
    assert not onnx_path(config).is_file()  # the one-pass graph was not needed
    images, ranges = inputs()
    assert graph.network_outputs(images, ranges).shape == (TURNS * 2, 256)
    np.testing.assert_allclose(graph.describe_tensors(images, ranges), exact.describe_tensors(images, ranges),
                               atol=1e-5, rtol=0)


def test_auto_also_races_the_turns_shared_out_to_single_threaded_sessions_which_give_the_same_rows(tmp_path):
    from lcpr_core.lcpr.runtime import SplitBackend
    from lcpr_core.lcpr.runtime.choose import SPLIT, _build_split

    target = tmp_path / "turned.pth"
    write_turn_average(write_net(tmp_path / "net.pth"), target, on=True)
    auto = Describer(ModelConfig(weights=str(target), precision="auto", threads=2))
    assert set(auto.choice.ms) | set(auto.choice.failed) == {"fp32", "bf16", "onnx", SPLIT}
    assert auto.choice.cosines[SPLIT] >= 0.99999
    exact = Describer(ModelConfig(weights=str(target), precision="fp32", threads=2))
    split = _build_split(auto.config, TurnedNetwork(exact.model))  # type: ignore[arg-type]
    assert isinstance(split, SplitBackend) and len(split.parts) == 2  # turns 0-2 and 3-5, one thread each
    images, ranges = inputs()
    np.testing.assert_allclose(split(images, ranges), exact.network_outputs(images, ranges), atol=1e-5, rtol=0)
    with pytest.raises(InvalidValueError, match=r"turns=\(2, 1\); accepted: ascending distinct turns"):
        TurnedNetwork(exact.model, turns=(2, 1))  # type: ignore[arg-type]


def test_a_file_asking_for_turn_averaging_on_another_rig_is_refused_by_name(tmp_path):
    net = write_net(tmp_path / "net.pth", InputConfig(num_cameras=2, image_size=(32, 64), range_size=(8, 72),
                                                      width=0.125))
    write_turn_average(net, tmp_path / "turned.pth", on=True)
    with pytest.raises(InvalidValueError, match="num_cameras=2"):
        Describer(ModelConfig(weights=str(tmp_path / "turned.pth"), precision="fp32"))
    assert not Describer(ModelConfig(weights=str(tmp_path / "turned.pth"), precision="fp32",
                                     turn_average=False)).turn_average


def test_the_entry_roundtrips_survives_the_float16_export_and_a_bad_value_is_refused(tmp_path):
    net = write_net(tmp_path / "net.pth")
    assert read_turn_average(net) is False
    target = tmp_path / "turned.pth"
    write_turn_average(net, target, on=True)
    assert torch.load(target, weights_only=True)[ENTRY] is True and read_turn_average(target) is True
    export_weights(target, tmp_path / "small.pth")
    assert read_turn_average(tmp_path / "small.pth") is True
    payload = torch.load(target, weights_only=True)
    payload[ENTRY] = 6
    torch.save(payload, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError, match=r"bad.pth.*'turn_average' entry 6; accepted: True or False"):
        read_turn_average(tmp_path / "bad.pth")


def test_the_recipe_adopts_turn_averaging_only_for_a_point_of_max_f1_at_no_real_cost_in_recall():
    def scores(r: float, f: float) -> dict:
        return {"single": {"mean_recall@1": 0.90, "mean_max_f1": 0.80},
                "turn average": {"mean_recall@1": r, "mean_max_f1": f}}

    assert adopt_turn_average(scores(0.90, 0.815))
    assert not adopt_turn_average(scores(0.95, 0.805))  # half a point of max F1 is not enough
    assert not adopt_turn_average(scores(0.885, 0.90))  # one and a half points of Recall@1 lost


def test_lcpr_train_turn_average_switches_the_entry_and_refuses_other_words(tmp_path, capsys):
    from lcpr_offline.lcpr_train import main as lcpr_train

    net = write_net(tmp_path / "net.pth")
    assert lcpr_train(["--turn-average", "on", str(net), str(tmp_path / "on.pth")]) == 0
    assert lcpr_train(["--turn-average", "off", str(tmp_path / "on.pth"), str(tmp_path / "off.pth")]) == 0
    assert read_turn_average(tmp_path / "on.pth") and not read_turn_average(tmp_path / "off.pth")
    assert lcpr_train(["--turn-average", "yes", str(net), str(tmp_path / "x.pth")]) == 2
    assert "--turn-average 'yes'; accepted: on, off" in capsys.readouterr().err
    assert not (tmp_path / "x.pth").exists()


def test_on_the_real_nuscenes_keyframe_the_bundled_averaged_descriptor_barely_moves_when_the_vehicle_turns(
        nuscenes_sample):
    from lcpr_core.lcpr.preprocess.dataset_files import find_nuscenes_keyframe
    from lcpr_core.pretrained import default_weights
    from lcpr_offline.lcpr_keyframe_demo import cosine

    images, points = find_nuscenes_keyframe(nuscenes_sample).read()
    moved = points.copy()
    moved[:, 1] -= 10.0  # the vehicle 10 m further on
    change = {}
    for averaged in (True, False):
        d = Describer(ModelConfig(weights=str(default_weights()), precision="fp32", threads=2, turn_average=averaged))
        assert d.turn_average is averaged  # the bundled file asks for it
        desc = d.describe(images, points)
        change[averaged] = (1 - cosine(desc, d.describe(*turn_frame(images, points, 1))),
                            1 - cosine(desc, d.describe(images, moved)))
    (turned, far), (turned_one_pass, _) = change[True], change[False]
    assert turned < turned_one_pass / 5 and turned < far / 50

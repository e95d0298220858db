"""The bundled weights files: where they are found, how every entry point names them (``bundled``, ``seeded``,
a file), the threshold a weights file carries, and which VSeq2PC set suits which depth."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lcpr_core.errors import CheckpointError, InvalidValueError
from lcpr_core.pretrained import (
    AUTO_DISTANCE,
    BUNDLED_MAX_DISTANCE,
    FALLBACK_MAX_DISTANCE,
    VSEQ2PC_DEPTH_KINDS,
    command_weights,
    default_vseq2pc_weights,
    default_weights,
    describe_weights,
    effective_max_distance,
    operating_threshold,
    resolve_vseq2pc_weights,
    resolve_weights,
    weight_folders,
    with_operating_threshold,
)
from lcpr_core.vseq2pc import Vseq2pcNet


def _parameters(net: Vseq2pcNet) -> dict[str, torch.Tensor]:
    return {f"{part}.{k}": v for part, model in (("sequence", net.sequence), ("descriptor", net.descriptor))
            for k, v in model.state_dict().items() if v.is_floating_point()}


def test_both_bundled_vseq2pc_sets_load_and_differ() -> None:
    nets = {}
    for kind in VSEQ2PC_DEPTH_KINDS:
        files = default_vseq2pc_weights(depth=kind)
        assert files is not None, f"the {kind}-depth VSeq2PC weights are missing from weights/"
        nets[kind] = _parameters(Vseq2pcNet.from_files(sequence=files[0], descriptor=files[1]))
    network, exact = nets["network"], nets["exact"]
    assert network.keys() == exact.keys()
    assert any(not torch.equal(network[k], exact[k]) for k in network), "the two sets are the same weights"


def test_the_default_vseq2pc_set_is_the_network_depth_one() -> None:
    assert default_vseq2pc_weights() == default_vseq2pc_weights(depth="network")


def test_an_unknown_depth_kind_is_refused_naming_the_accepted_ones() -> None:
    with pytest.raises(InvalidValueError, match=r"'lidar'.*exact, network"):
        default_vseq2pc_weights(depth="lidar")


def test_bundled_names_the_shipped_file_and_seeded_names_no_file() -> None:
    assert resolve_weights("bundled") == default_weights()
    assert resolve_weights("seeded") == ""
    assert resolve_weights("/some/file.pth") == "/some/file.pth"
    assert resolve_weights("") == ""  # the Python API's "no weights" is unchanged


def test_an_empty_setting_on_a_command_line_means_the_bundled_weights_unless_imagenet_blocks_are_asked_for() -> None:
    assert command_weights("") == "bundled"
    assert command_weights("", imagenet="resnet18.pth") == ""
    assert command_weights("seeded") == "seeded"


def test_the_bundled_file_carries_its_operating_threshold() -> None:
    weights = default_weights()
    assert weights is not None
    assert operating_threshold(weights) == BUNDLED_MAX_DISTANCE


def test_automatic_max_distance_verifies_every_candidate_and_otherwise_takes_the_files_threshold() -> None:
    assert effective_max_distance(AUTO_DISTANCE, 0.7, verified=True) == FALLBACK_MAX_DISTANCE
    assert effective_max_distance(AUTO_DISTANCE, 0.7, verified=False) == 0.7
    assert effective_max_distance(AUTO_DISTANCE, None, verified=False) == FALLBACK_MAX_DISTANCE
    assert effective_max_distance(0.5, 0.7, verified=False) == 0.5


def test_a_file_without_a_threshold_has_none_and_a_bad_one_is_refused_naming_it(tmp_path: Path) -> None:
    plain = tmp_path / "plain.pth"
    torch.save({"net": {}}, plain)
    assert operating_threshold(str(plain)) is None
    assert operating_threshold("") is None
    bad = tmp_path / "bad.pth"
    torch.save({"net": {}, "operating_threshold": {"max_distance": -3.0}}, bad)
    with pytest.raises(CheckpointError, match="-3.0"):
        operating_threshold(str(bad))
    marked = tmp_path / "marked.pth"
    torch.save(with_operating_threshold({"net": {}}, max_distance=0.6, chosen_on="a test"), marked)
    assert operating_threshold(str(marked)) == 0.6
    with pytest.raises(InvalidValueError, match="nan"):
        with_operating_threshold({}, max_distance=float("nan"), chosen_on="x")


def test_a_missing_bundled_file_names_where_it_was_looked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("lcpr_core.pretrained.default_weights", lambda: None)
    with pytest.raises(CheckpointError, match="looked in"):
        resolve_weights("bundled")


def test_an_ament_prefix_is_searched_for_a_colcon_install_under_a_system_ros(monkeypatch: pytest.MonkeyPatch,
                                                                            tmp_path: Path) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "install" / "lcpr_loop_closure"))
    assert tmp_path / "install" / "lcpr_loop_closure" / "share" / "lcpr_loop_closure" / "weights" in weight_folders()


def test_the_weights_line_says_what_was_loaded() -> None:
    assert "bundled weights" in describe_weights(str(default_weights()))
    assert "random" in describe_weights("")


def test_vseq2pc_settings_name_one_set_in_both_fields_or_two_files() -> None:
    assert resolve_vseq2pc_weights("bundled", "bundled") == default_vseq2pc_weights(depth="network")
    assert resolve_vseq2pc_weights("", "") == default_vseq2pc_weights(depth="network")
    assert resolve_vseq2pc_weights("bundled-exact", "bundled-exact") == default_vseq2pc_weights(depth="exact")
    assert resolve_vseq2pc_weights("seeded", "seeded") is None
    assert resolve_vseq2pc_weights("a.pth", "b.pth") == ("a.pth", "b.pth")
    with pytest.raises(InvalidValueError, match="'bundled'.*'b.pth'"):
        resolve_vseq2pc_weights("bundled", "b.pth")

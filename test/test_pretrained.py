"""The bundled weights files: where they are found and which VSeq2PC set suits which depth."""
from __future__ import annotations

import pytest
import torch

from lcpr_core.errors import InvalidValueError
from lcpr_core.pretrained import VSEQ2PC_DEPTH_KINDS, default_vseq2pc_weights
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

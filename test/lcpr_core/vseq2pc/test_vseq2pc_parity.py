"""SequenceModel and DescriptorModel reproduce the authors' released VSeq2PC networks."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from conftest import reference_seed, reference_sets
from lcpr_core import DescriptorModel, SequenceModel

TOL = 1e-5


@pytest.fixture(scope="module")
def keys(shared: Path) -> dict[str, dict[str, list[int]]]:
    return json.loads((shared / "reference" / "vseq2pc" / "keys.json").read_text())


def test_both_models_have_the_released_parameter_names_and_shapes(keys):
    for model, group in ((SequenceModel(), "sequence_model"), (DescriptorModel(), "descriptor_model")):
        state = model.state_dict()
        assert {k: list(v.shape) for k, v in state.items()} == keys[group]


@pytest.mark.parametrize("ref_file", reference_sets("vseq2pc"), ids=lambda p: p.stem)
def test_features_descriptors_and_scores_match_the_released_code(ref_file: Path, keys, detweights):
    seed = reference_seed(ref_file)
    ref = np.load(ref_file)
    seq, desc = SequenceModel().eval(), DescriptorModel().eval()
    seq.load_state_dict(detweights.det_state_dict(keys["sequence_model"], seed))
    desc.load_state_dict(detweights.det_state_dict(keys["descriptor_model"], seed))
    assert sum(p.numel() for p in seq.parameters()) == int(ref["params_sequence_model"])
    assert sum(p.numel() for p in desc.parameters()) == int(ref["params_descriptor_model"])

    frames, slices = torch.from_numpy(ref["frames"]), torch.from_numpy(ref["slices"])
    b, n = slices.shape[:2]
    with torch.inference_mode():
        f_seq = seq(frames)
        d_seq = desc.sequence_descriptor(f_seq, frames[:, 0])
        d_slices = desc.scan_descriptor(slices.reshape(b * n, *slices.shape[2:])).view(b, n, -1)
        scores = desc.score(d_seq[:, None], d_slices)
        # The reference's "rolled" pairs query b with torch.roll(slices, 1, 0)[b].
        rolled = desc.score(d_seq[:, None], d_slices.roll(1, dims=0))
    close: dict[str, Any] = dict(atol=TOL, rtol=0)
    np.testing.assert_allclose(f_seq.numpy(), ref["sequence_feature"], **close)
    np.testing.assert_allclose(d_seq.numpy(), ref["sequence_descriptor"], **close)
    np.testing.assert_allclose(d_slices.numpy(), ref["slice_descriptors"], **close)
    np.testing.assert_allclose(scores.numpy(), ref["slice_scores"], **close)
    np.testing.assert_allclose(rolled.numpy(), ref["slice_scores_rolled"], **close)
    np.testing.assert_allclose(scores.max(dim=1).values.numpy(), ref["scan_score"], **close)


def test_eval_mode_is_deterministic_and_training_masks_tokens():
    torch.manual_seed(0)
    model = SequenceModel()
    frames = torch.rand(2, 4, 12, 90)
    model.eval()
    with torch.no_grad():
        a, b = model(frames), model(frames)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    model.train()
    with torch.no_grad():
        c, d = model(frames), model(frames)
    assert not torch.equal(c, d)  # a different 10% of the tokens is masked each time
    assert c.shape == (2, 12, 90) and c.min() >= 0 and c.max() <= 1


def test_wrong_frame_shapes_are_refused():
    with pytest.raises(ValueError, match=r"expected B x 4 x 12 x 90"):
        SequenceModel()(torch.zeros(1, 3, 12, 90))

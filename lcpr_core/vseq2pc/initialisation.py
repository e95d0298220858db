"""The initialisation training starts from (and the "untrained" baseline uses).

PyTorch's default initialisation leaves the sequence model's clamped output saturated:
on real features almost every cell of F_seq is exactly 0 or 1, where clamp passes no
gradient, so reconstruction pretraining cannot start. Training therefore initialises
the sequence model MAE-style (xavier-uniform linear and patchify weights, zero biases,
unit LayerNorms, tokens and position embeddings ~ N(0, 0.02)) and starts its head
small (weights ~ N(0, 0.01), bias 0.1: about the mean of a structure feature), so about
half of F_seq begins inside (0, 1). The descriptor model keeps PyTorch's defaults.

Too large a sequence-model learning rate (Adam's first steps move every weight by about
the learning rate) can push F_seq back into saturation, where it stays: on the synthetic
drives 1.5e-4 worked, 5e-3 did not.
"""
from __future__ import annotations

import torch
from torch import nn

from .models import DescriptorModel, SequenceModel

__all__ = ["HEAD_BIAS", "initialise_sequence_model", "seeded_models"]

HEAD_BIAS = 0.1


@torch.no_grad()
def initialise_sequence_model(model: SequenceModel) -> SequenceModel:
    """Re-initialise ``model`` in place (uses torch's global RNG) and return it."""
    for module in model.modules():
        if isinstance(module, nn.Linear):
            nn.init.xavier_uniform_(module.weight)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.LayerNorm):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)
    conv = model.encoder.patchify.conv1
    nn.init.xavier_uniform_(conv.weight.view(conv.weight.shape[0], -1))
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    nn.init.normal_(model.encoder.cls_token, std=0.02)
    nn.init.normal_(model.decoder.mask_token, std=0.02)
    nn.init.trunc_normal_(model.encoder.pos_embedding, std=0.02)
    nn.init.trunc_normal_(model.decoder.pos_embedding, std=0.02)
    nn.init.normal_(model.decoder.head.weight, std=0.01)
    nn.init.constant_(model.decoder.head.bias, HEAD_BIAS)
    return model


def seeded_models(seed: int) -> tuple[SequenceModel, DescriptorModel]:
    """Both models, initialised for training from ``seed`` (torch's global RNG state is left as it was)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        seq = initialise_sequence_model(SequenceModel())
        desc = DescriptorModel()
    return seq, desc

"""The models' pair scores and the joint loss (BCE on the max-slice logit + contrastive on its distance), and
the optional ranking term (each query's positives against its negatives, softmax over the max-slice logits)."""
from __future__ import annotations

import logging

import torch
import torch.nn.functional as F

from ..models import DescriptorModel, SequenceModel
from ..net import scan_slice_descriptors, slice_tensor
from ..retrieval import head_logits

log = logging.getLogger("lcpr_core.vseq2pc.training")

# ---------------------------------------------------------------------- model pieces
def describe(seq: SequenceModel, desc: DescriptorModel, frames: torch.Tensor, lidar: torch.Tensor, *,
             mixed_batch_norm: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """B x 4 x 12 x 90 sequences and M x 12 x 360 scans -> B x 288 and M x 8 x 288 descriptors (gradients kept).

    ``mixed_batch_norm``: sequences and scan slices pass the shared tower together
    (:meth:`DescriptorModel.descriptors`), so training normalises them as eval mode does."""
    f_seq = seq(frames)
    if not mixed_batch_norm:
        return desc.sequence_descriptor(f_seq, frames[:, 0]), scan_slice_descriptors(desc, lidar)
    m = lidar.shape[0]
    d_seq, d_slices = desc.descriptors(f_seq, frames[:, 0], slice_tensor(lidar).reshape(m * 8, *lidar.shape[1:]))
    return d_seq, d_slices.view(m, 8, -1)


def pair_logits(seq: SequenceModel, desc: DescriptorModel, frames: torch.Tensor, lidar: torch.Tensor, *,
                mixed_batch_norm: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """B x 4 x 12 x 90 sequences and B x S x 12 x 360 scans (S per sequence) -> max-slice logits (B, S) and
    the squared descriptor distance to the best slice (B, S)."""
    b, s = lidar.shape[:2]
    d_seq, d_scan = describe(seq, desc, frames, lidar.reshape(b * s, *lidar.shape[2:]),
                             mixed_batch_norm=mixed_batch_norm)
    return _best_slice(desc, d_seq, d_scan.view(b, s, 8, -1))


def cross_logits(seq: SequenceModel, desc: DescriptorModel, frames: torch.Tensor, lidar: torch.Tensor, *,
                 mixed_batch_norm: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """B sequences against every one of M scans (M x 12 x 360) -> logits and squared distances (B, M)."""
    d_seq, d_scan = describe(seq, desc, frames, lidar, mixed_batch_norm=mixed_batch_norm)  # B x 288, M x 8 x 288
    return _best_slice(desc, d_seq, d_scan.expand(len(d_seq), -1, -1, -1))


def _best_slice(desc: DescriptorModel, d_seq: torch.Tensor, d_scan: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    values, indices = head_logits(desc, d_seq[:, None, None, :], d_scan)  # B x S
    chosen = torch.gather(d_scan, 2, indices[..., None, None].expand(-1, -1, 1, d_scan.shape[-1]))[:, :, 0]
    sq = ((d_seq[:, None, :] - chosen) ** 2).sum(dim=-1)
    return values, sq


def place_loss(logits: torch.Tensor, sq_dist: torch.Tensor, labels: torch.Tensor, *, margin: float,
               weights: torch.Tensor | None = None) -> torch.Tensor:
    """BCE-with-logits + y d^2 + (1 - y) relu(margin - d)^2, averaged (weighted when ``weights`` sum to 1)."""
    d = torch.sqrt(sq_dist + 1e-12)
    bce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    per_pair = bce + labels * sq_dist + (1 - labels) * F.relu(margin - d) ** 2
    return per_pair.mean() if weights is None else (per_pair * weights).sum()


def ranking_loss(logits: torch.Tensor, positive: torch.Tensor, negative: torch.Tensor) -> torch.Tensor:
    """Mean over the queries (rows) with at least one positive and one negative scan of
    -log(sum exp(positive logits) / sum exp(positive and negative logits)); 0 when no row has both.

    logits, positive, negative: B x S (masks bool; scans in neither mask are ignored). What Recall@1
    asks for: the query's own place scored above every other place, not each pair on its own.
    """
    usable = positive.any(dim=1) & negative.any(dim=1)
    if not bool(usable.any()):
        return logits.sum() * 0.0
    lo = torch.finfo(logits.dtype).min
    x, pos, neg = logits[usable], positive[usable], negative[usable]
    top = torch.logsumexp(x.masked_fill(~pos, lo), dim=1)
    every = torch.logsumexp(x.masked_fill(~(pos | neg), lo), dim=1)
    return (every - top).mean()

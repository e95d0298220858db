"""The triplet margin loss of the paper's Eq. 8, over a variable number of negatives per query."""
from __future__ import annotations

from collections.abc import Sequence

import torch

from ...errors import InvalidValueError


def triplet_loss(
    query: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor, *, margin: float = 0.5
) -> torch.Tensor:
    """mean_i [d(q, p) - d(q, n_i) + m]_+ for one query: D, D and K x D descriptors -> scalar."""
    d_pos = torch.linalg.vector_norm(query - positive)
    d_neg = torch.linalg.vector_norm(negatives - query.unsqueeze(0), dim=1)
    return torch.clamp(d_pos - d_neg + margin, min=0).mean()


def batch_triplet_loss(descriptors: torch.Tensor, counts: Sequence[int], *, margin: float = 0.5) -> torch.Tensor:
    """Mean over queries of :func:`triplet_loss`.

    ``descriptors`` stacks, for each query in turn, [query, positive, negatives...];
    ``counts[i]`` is the number of negatives of query i.
    """
    losses = []
    at = 0
    for k in counts:
        losses.append(triplet_loss(descriptors[at], descriptors[at + 1], descriptors[at + 2:at + 2 + k],
                                   margin=margin))
        at += 2 + k
    if at != len(descriptors):
        raise InvalidValueError(f"{len(descriptors)} descriptors but counts {list(counts)} account for {at}")
    return torch.stack(losses).mean()

"""NetVLAD aggregation with a linear projection and context gating (released key names)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ContextGating(nn.Module):
    """x * sigmoid(BN(x @ W))."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gating_weights = nn.Parameter(torch.randn(dim, dim) / dim**0.5)
        self.bn1 = nn.BatchNorm1d(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # B x D
        return x * torch.sigmoid(self.bn1(x @ self.gating_weights))


class NetVLAD(nn.Module):
    """B x D x 1 x M (M samples) -> B x output_dim.

    The number of samples is read from the input, so any feature width works.
    ``bn2`` exists in the released checkpoints but is never applied; it is kept so
    that they load.
    """

    def __init__(self, feature_dim: int = 256, clusters: int = 32, output_dim: int = 128) -> None:
        super().__init__()
        scale = 1 / feature_dim**0.5
        self.cluster_weights = nn.Parameter(torch.randn(feature_dim, clusters) * scale)
        self.cluster_weights2 = nn.Parameter(torch.randn(1, feature_dim, clusters) * scale)
        self.hidden1_weights = nn.Parameter(
            torch.randn(clusters * feature_dim, output_dim) / (clusters * feature_dim) ** 0.5
        )
        self.bn1 = nn.BatchNorm1d(clusters)
        self.bn2 = nn.BatchNorm1d(output_dim)
        self.context_gating = ContextGating(output_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, d, _, m = x.shape
        x = x.reshape(b, d, m).transpose(1, 2)  # B x M x D
        k = self.cluster_weights.shape[1]
        a = self.bn1((x @ self.cluster_weights).reshape(b * m, k)).reshape(b, m, k)
        a = torch.softmax(a, dim=-1)  # B x M x K
        centre = a.sum(dim=1, keepdim=True) * self.cluster_weights2  # B x D x K
        vlad = (a.transpose(1, 2) @ x).transpose(1, 2) - centre  # B x D x K
        vlad = F.normalize(vlad, dim=1)
        vlad = F.normalize(vlad.reshape(b, d * k), dim=1)  # index d * K + k
        return self.context_gating(vlad @ self.hidden1_weights)

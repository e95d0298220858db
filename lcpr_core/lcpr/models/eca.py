"""Efficient channel attention on a descriptor vector."""
from __future__ import annotations

import torch
from torch import nn


class ECA(nn.Module):
    """B x C -> B x C: x * sigmoid(conv1d over the channel axis)."""

    def __init__(self, kernel_size: int = 3) -> None:
        super().__init__()
        self.conv = nn.Conv1d(1, 1, kernel_size, padding=kernel_size // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # B x C
        return x * torch.sigmoid(self.conv(x.unsqueeze(1)).squeeze(1))

"""Vertical compression (VC) layer: per-pixel gating, max over height, 1-D refinement."""
from __future__ import annotations

import torch
from torch import nn


class VertConv(nn.Module):
    """B x C_in x H x W -> B x C_out x W.

    ``compress`` (1x1 convs + max over height) and ``refine`` (the 1-D convs) are
    separate methods so that a caller may compress several images and join their
    columns before refining, which is how the camera panorama is built without
    copying the full-height feature maps.
    """

    def __init__(self, in_ch: int, mid_ch: int, out_ch: int) -> None:
        super().__init__()
        self.input_conv = nn.Sequential(
            nn.Conv2d(in_ch, in_ch, 1), nn.Sigmoid(), nn.Conv2d(in_ch, in_ch, 1)
        )
        self.reduce_conv = nn.Sequential(
            nn.Conv1d(in_ch, mid_ch, 1, bias=False), nn.BatchNorm1d(mid_ch), nn.ReLU(inplace=True)
        )
        self.conv = nn.Sequential(
            nn.Conv1d(mid_ch, mid_ch, 3, padding=1, bias=False),
            nn.BatchNorm1d(mid_ch),
            nn.ReLU(inplace=True),
            nn.Conv1d(mid_ch, mid_ch, 3, padding=1, bias=False),
            nn.BatchNorm1d(mid_ch),
            nn.ReLU(inplace=True),
        )
        self.out_conv = nn.Sequential(
            nn.Conv1d(mid_ch, out_ch, 1), nn.BatchNorm1d(out_ch), nn.ReLU(inplace=True)
        )

    def compress(self, x: torch.Tensor) -> torch.Tensor:  # B x C x H x W -> B x C x W
        return self.input_conv(x).amax(dim=2)

    def refine(self, x: torch.Tensor) -> torch.Tensor:  # B x C_in x W -> B x C_out x W
        x = self.reduce_conv(x)
        x = x + self.conv(x)
        return self.out_conv(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # B x C_in x H x W -> B x C_out x W
        return self.refine(self.compress(x))

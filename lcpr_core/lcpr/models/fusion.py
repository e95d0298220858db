"""Vertically Compressed Transformer Fusion (VCTF) and the camera panorama layout."""
from __future__ import annotations

import torch
from torch import nn

from .attention import MultiHeadSelfAttention
from .vertconv import VertConv


def to_panorama(columns: torch.Tensor, num_cameras: int) -> torch.Tensor:
    """(B*N) x C x W -> B x C x (N*W); camera k occupies columns k*W .. (k+1)*W-1."""
    bn, c, w = columns.shape
    b = bn // num_cameras
    return columns.view(b, num_cameras, c, w).permute(0, 2, 1, 3).reshape(b, c, num_cameras * w)


def from_panorama(panorama: torch.Tensor, num_cameras: int) -> torch.Tensor:
    """B x C x (N*W) -> (B*N) x C x W, the inverse of :func:`to_panorama`."""
    b, c, nw = panorama.shape
    w = nw // num_cameras
    return panorama.view(b, c, num_cameras, w).permute(0, 2, 1, 3).reshape(b * num_cameras, c, w)


def camera_columns(vert_conv: VertConv, features: torch.Tensor, num_cameras: int) -> torch.Tensor:
    """(B*N) x C x H x W camera features -> B x C_out x (N*W) panorama columns.

    The 1x1 convolutions and the max over height act on each pixel column alone, so
    they run per camera and only the compressed columns are joined: the same result
    as compressing the full-height panorama, without copying it.
    """
    return vert_conv.refine(to_panorama(vert_conv.compress(features), num_cameras))


class Fusion(nn.Module):
    """Fuses camera and LiDAR features of C channels with self-attention over their columns.

    Returns the two residuals to add to the branch features, constant over the height:
    (B*N) x C x 1 x W_i for the cameras and B x C x 1 x W_l for the LiDAR.
    """

    def __init__(self, channels: int, heads: int = 4) -> None:
        super().__init__()
        self.v_conv_i = VertConv(channels, channels // 2, channels)
        self.v_conv_l = VertConv(channels, channels // 2, channels)
        self.atten = MultiHeadSelfAttention(channels, heads)

    def forward(
        self, camera: torch.Tensor, lidar: torch.Tensor, num_cameras: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        cam = camera_columns(self.v_conv_i, camera, num_cameras)  # B x C x N*W_i
        lid = self.v_conv_l(lidar)  # B x C x W_l
        tokens = torch.cat([cam, lid], dim=2).transpose(1, 2)  # B x L x C
        tokens = tokens + self.atten(tokens)
        cam_out, lid_out = tokens.transpose(1, 2).split([cam.shape[2], lid.shape[2]], dim=2)
        return from_panorama(cam_out, num_cameras).unsqueeze(2), lid_out.unsqueeze(2)

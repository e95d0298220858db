"""LCPR: six camera images + one LiDAR range image -> a 256-d, yaw-invariant descriptor."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import InputShapeError, InvalidValueError
from .eca import ECA
from .fusion import Fusion, camera_columns
from .netvlad import NetVLAD
from .resnet import resnet_layer
from .vertconv import VertConv

STAGE_CHANNELS = (64, 128, 256, 512)
COMPRESSED_CHANNELS = 256  # v_conv_i / v_conv_l output and NetVLAD feature size (released)
CHANNEL_MULTIPLE = 8  # scaled channel counts are rounded to this (attention heads and C/2 must divide)


def scaled_channels(channels: int, width: float) -> int:
    """``channels * width`` rounded to a multiple of 8 (at least 8); width 1.0 gives ``channels``."""
    return max(CHANNEL_MULTIPLE, int(round(channels * width / CHANNEL_MULTIPLE)) * CHANNEL_MULTIPLE)


@dataclass(frozen=True)
class LcprOutput:
    descriptor: torch.Tensor  # B x 256, unit length
    camera: torch.Tensor  # B x 128, camera sub-descriptor (netvlad_i)
    lidar: torch.Tensor  # B x 128, LiDAR sub-descriptor (netvlad_l)


class LCPR(nn.Module):
    """The released LCPR network, with its parameter names and shapes.

    Args:
        num_cameras: cameras in the panorama (released: 6, nuScenes order).
        image_size: (height, width) of each camera image (released: 256 x 704).
        range_size: (height, width) of the range image (released: 32 x 1056).
        width: channel multiplier for every convolution, fusion and NetVLAD feature size
            (released: 1.0; 0.25-0.5 for CPU training). Counts are rounded to multiples
            of 8. Parameter names never change and the descriptor stays 256-d; only
            width 1.0 has the released shapes.

    The computation has no size baked in: these options only define the inputs
    :meth:`forward` accepts (and :meth:`example_inputs` makes). Widths must be
    divisible by 32 (camera) and 8 (range image) for the stages to line up.
    """

    def __init__(
        self,
        *,
        num_cameras: int = 6,
        image_size: tuple[int, int] = (256, 704),
        range_size: tuple[int, int] = (32, 1056),
        width: float = 1.0,
    ) -> None:
        super().__init__()
        _check_sizes(num_cameras, image_size, range_size)
        if not (isinstance(width, (int, float)) and 0 < width <= 4):
            raise InvalidValueError(
                f"width={width!r}; accepted: a channel multiplier in (0, 4], e.g. 1.0 (released) or 0.25")
        self.num_cameras = num_cameras
        self.image_size = tuple(image_size)
        self.range_size = tuple(range_size)
        self.width = float(width)
        c1, c2, c3, c4 = (scaled_channels(c, width) for c in STAGE_CHANNELS)
        compressed = scaled_channels(COMPRESSED_CHANNELS, width)

        self.conv1_i = nn.Conv2d(3, c1, 7, stride=2, padding=3, bias=False)
        self.bn1_i = nn.BatchNorm2d(c1)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.conv_l = nn.Conv2d(1, c1, 1)
        self.layer1_i = resnet_layer(c1, c1, stride=1)
        self.layer2_i = resnet_layer(c1, c2, stride=2)
        self.layer2_l = resnet_layer(c1, c2, stride=2)
        self.layer3_i = resnet_layer(c2, c3, stride=2)
        self.layer3_l = resnet_layer(c2, c3, stride=2)
        self.layer4_i = resnet_layer(c3, c4, stride=2)
        self.layer4_l = resnet_layer(c3, c4, stride=2)
        self.fusion1 = Fusion(c1)
        self.fusion2 = Fusion(c2)
        self.fusion3 = Fusion(c3)
        self.fusion4 = Fusion(c4)
        self.v_conv_i = VertConv(c4, compressed, compressed)
        self.v_conv_l = VertConv(c4, compressed, compressed)
        self.netvlad_i = NetVLAD(compressed, 32, 128)
        self.netvlad_l = NetVLAD(compressed, 32, 128)
        self.eca = ECA(3)

    @property
    def descriptor_dim(self) -> int:
        return 2 * self.netvlad_i.hidden1_weights.shape[1]

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero inputs of the configured sizes: B x N x 3 x H x W and B x 1 x h x w."""
        images = torch.zeros(batch, self.num_cameras, 3, *self.image_size)
        return images, torch.zeros(batch, 1, *self.range_size)

    def forward(self, images: torch.Tensor, range_image: torch.Tensor) -> torch.Tensor:
        """B x N x 3 x H x W images, B x 1 x h x w ranges -> B x 256 unit descriptors."""
        return self.describe(images, range_image).descriptor

    def describe(self, images: torch.Tensor, range_image: torch.Tensor) -> LcprOutput:
        """The descriptor together with the camera and LiDAR sub-descriptors."""
        self._check_inputs(images, range_image)
        return self.describe_from_stem(self.camera_stem(images), range_image, images.shape[1])

    def camera_stem(self, images: torch.Tensor) -> torch.Tensor:
        """B x N x 3 x H x W images -> (B*N) x C1 x H/4 x W/4: the layers that see each camera image alone
        (conv1_i, bn1_i, max pool, layer1_i), before the first fusion with the LiDAR branch.

        Exposed so that the six turns of one frame (the same images, cameras rolled) can share it:
        :mod:`lcpr_core.lcpr.turn_average` computes it once and rolls the features instead.
        """
        b, n = images.shape[:2]
        cam = images.reshape(b * n, *images.shape[2:]).contiguous(memory_format=torch.channels_last)
        cam = self.maxpool(self.relu(self.bn1_i(self.conv1_i(cam))))
        return self.layer1_i(cam)  # (B*N) x C1 x H/4 x W/4 (C1 = 64 at width 1)

    def describe_from_stem(self, cam: torch.Tensor, range_image: torch.Tensor, n: int) -> LcprOutput:
        """:meth:`describe` after :meth:`camera_stem`: (B*N) x C1 x H/4 x W/4 camera features of N cameras
        per frame and B x 1 x h x w ranges -> the descriptors."""
        lid = self.conv_l(range_image.contiguous(memory_format=torch.channels_last))  # B x C1 x h x w
        stages = (
            (None, None, self.fusion1),
            (self.layer2_i, self.layer2_l, self.fusion2),
            (self.layer3_i, self.layer3_l, self.fusion3),
            (self.layer4_i, self.layer4_l, self.fusion4),
        )
        for layer_i, layer_l, fusion in stages:
            if layer_i is not None and layer_l is not None:  # both None at the first stage
                cam, lid = layer_i(cam), layer_l(lid)
            cam_res, lid_res = fusion(cam, lid, n)
            cam, lid = cam + cam_res, lid + lid_res
        cam_desc = self.netvlad_i(camera_columns(self.v_conv_i, cam, n).unsqueeze(2))  # B x 128
        lid_desc = self.netvlad_l(self.v_conv_l(lid).unsqueeze(2))  # B x 128
        desc = F.normalize(self.eca(torch.cat([cam_desc, lid_desc], dim=1)), dim=1)
        return LcprOutput(descriptor=desc, camera=cam_desc, lidar=lid_desc)

    def _check_inputs(self, images: torch.Tensor, range_image: torch.Tensor) -> None:
        want_img = (self.num_cameras, 3, *self.image_size)
        if images.dim() != 5 or tuple(images.shape[1:]) != want_img:
            raise InputShapeError(
                f"images have shape {tuple(images.shape)}; expected B x {' x '.join(map(str, want_img))}"
            )
        want_rng = (images.shape[0], 1, *self.range_size)
        if tuple(range_image.shape) != want_rng:
            raise InputShapeError(
                f"range_image has shape {tuple(range_image.shape)}; expected {' x '.join(map(str, want_rng))}"
            )


def _check_sizes(num_cameras: int, image_size: tuple[int, int], range_size: tuple[int, int]) -> None:
    if num_cameras < 1:
        raise InvalidValueError(f"num_cameras={num_cameras}; it must be at least 1")
    if len(image_size) != 2 or image_size[0] % 32 or image_size[1] % 32:
        raise InvalidValueError(f"image_size={image_size}; height and width must be multiples of 32 (e.g. 256 x 704)")
    if len(range_size) != 2 or range_size[0] % 8 or range_size[1] % 8:
        raise InvalidValueError(f"range_size={range_size}; height and width must be multiples of 8 (e.g. 32 x 1056)")

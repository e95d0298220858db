"""The LCPR forward pass written the straightforward way, for side-by-side timing.

Not the authors' code (it is not ours to copy): the same function on the same
parameters, computed as a direct reading of the spec does it and as research code
typically does: NCHW tensors, the camera panorama materialised at full height
before each vertical compression, attention as explicit matmul + softmax, and the
fused columns copied back over the height with ``repeat``. ``benchmarks/tools/lcpr_forward.py``
times it beside :class:`lcpr_core.LCPR` and checks that both give the same descriptors.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .attention import MultiHeadSelfAttention
from .fusion import Fusion
from .lcpr import LCPR
from .vertconv import VertConv


def panorama(x: torch.Tensor, n: int) -> torch.Tensor:  # (B*N) x C x H x W -> B x C x H x N*W
    bn, c, h, w = x.shape
    return x.view(bn // n, n, c, h, w).permute(0, 2, 3, 1, 4).contiguous().view(bn // n, c, h, n * w)


def unpanorama(x: torch.Tensor, n: int) -> torch.Tensor:  # B x C x H x N*W -> (B*N) x C x H x W
    b, c, h, nw = x.shape
    return x.view(b, c, h, n, nw // n).permute(0, 3, 1, 2, 4).contiguous().view(b * n, c, h, nw // n)


def vert_conv(vc: VertConv, x: torch.Tensor) -> torch.Tensor:  # B x C x H x W -> B x C' x W
    x = vc.input_conv(x)
    x = torch.max(x, dim=2)[0]
    x = vc.reduce_conv(x)
    x = x + vc.conv(x)
    return vc.out_conv(x)


def attention(att: MultiHeadSelfAttention, x: torch.Tensor) -> torch.Tensor:  # B x L x C
    b, length, c = x.shape
    heads, d = att.heads, c // att.heads

    def split(t: torch.Tensor) -> torch.Tensor:
        return t.view(b, length, heads, d).transpose(1, 2)

    q, k, v = split(att.w_q(x)), split(att.w_k(x)), split(att.w_v(x))
    score = torch.softmax(q @ k.transpose(2, 3) / d**0.5, dim=-1)
    out = (score @ v).transpose(1, 2).contiguous().view(b, length, c)
    return att.w_concat(out)


def fusion(fu: Fusion, cam: torch.Tensor, lid: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    pano = panorama(cam, n)
    xi, xl = vert_conv(fu.v_conv_i, pano), vert_conv(fu.v_conv_l, lid)
    x = torch.cat([xi, xl], dim=2).permute(0, 2, 1)
    x = x + attention(fu.atten, x)
    x = x.permute(0, 2, 1)
    fi, fl = x[:, :, : xi.shape[2]], x[:, :, xi.shape[2]:]
    fi = fi.unsqueeze(2).repeat(1, 1, pano.shape[2], 1)
    fl = fl.unsqueeze(2).repeat(1, 1, lid.shape[2], 1)
    return unpanorama(fi, n), fl


def baseline_forward(m: LCPR, images: torch.Tensor, ranges: torch.Tensor) -> torch.Tensor:
    b, n = images.shape[:2]
    x_i = images.view(b * n, *images.shape[2:])
    x_i = m.layer1_i(m.maxpool(m.relu(m.bn1_i(m.conv1_i(x_i)))))
    x_l = m.conv_l(ranges)
    fi, fl = fusion(m.fusion1, x_i, x_l, n)
    x_i, x_l = x_i + fi, x_l + fl
    for li, ll, fu in ((m.layer2_i, m.layer2_l, m.fusion2), (m.layer3_i, m.layer3_l, m.fusion3),
                       (m.layer4_i, m.layer4_l, m.fusion4)):
        x_i, x_l = li(x_i), ll(x_l)
        fi, fl = fusion(fu, x_i, x_l, n)
        x_i, x_l = x_i + fi, x_l + fl
    d_i = m.netvlad_i(vert_conv(m.v_conv_i, panorama(x_i, n)).unsqueeze(2))
    d_l = m.netvlad_l(vert_conv(m.v_conv_l, x_l).unsqueeze(2))
    return F.normalize(m.eca(torch.cat([d_i, d_l], dim=1)), dim=1)

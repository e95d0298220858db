"""Multi-head self-attention with the released parameter names (w_q, w_k, w_v, w_concat)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import InvalidValueError


class MultiHeadSelfAttention(nn.Module):
    """B x L x C -> B x L x C; heads take consecutive channel groups, no mask, no dropout."""

    def __init__(self, channels: int, heads: int = 4) -> None:
        super().__init__()
        if channels % heads:
            raise InvalidValueError(f"channels={channels} is not divisible by heads={heads}")
        self.heads = heads
        self.w_q = nn.Linear(channels, channels)
        self.w_k = nn.Linear(channels, channels)
        self.w_v = nn.Linear(channels, channels)
        self.w_concat = nn.Linear(channels, channels)

    def _split(self, x: torch.Tensor) -> torch.Tensor:  # B x L x C -> B x heads x L x C/heads
        b, length, c = x.shape
        return x.view(b, length, self.heads, c // self.heads).transpose(1, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # B x L x C
        q, k, v = (self._split(w(x)) for w in (self.w_q, self.w_k, self.w_v))
        out = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d)) v, fused
        b, _, length, d = out.shape
        return self.w_concat(out.transpose(1, 2).reshape(b, length, self.heads * d))

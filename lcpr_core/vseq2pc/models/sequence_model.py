"""VSeq2PC sequence model: K structure features of a camera sequence -> one fused feature.

A masked-autoencoder-style transformer over tokens of two adjacent sectors of one
semantic class row. Masking (a random ``mask_ratio`` of the tokens dropped before
the encoder) happens only in training; in eval mode every token is kept, so
retrieval is deterministic.
"""
from __future__ import annotations

import torch
from torch import nn

from ...errors import InputShapeError, InvalidValueError
from .transformer import Block


class Patchify(nn.Module):
    """B x K x R x S -> B x (R * S/2) x C tokens, class-row major, sector minor."""

    def __init__(self, frames: int, dim: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv1d(frames, dim, kernel_size=2, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, k, rows, sectors = x.shape
        per_row = x.permute(0, 2, 1, 3).reshape(b * rows, k, sectors)  # (B*R) x K x S
        tokens = self.conv1(per_row)  # (B*R) x C x S/2
        return tokens.view(b, rows, -1, tokens.shape[-1]).permute(0, 1, 3, 2).reshape(b, -1, tokens.shape[1])


class Encoder(nn.Module):
    def __init__(self, frames: int, rows: int, sectors: int, dim: int, heads: int, depth: int) -> None:
        super().__init__()
        tokens = rows * sectors // 2
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embedding = nn.Parameter(torch.randn(tokens, 1, dim) * 0.02)  # T x 1 x C
        self.patchify = Patchify(frames, dim)
        self.transformer = nn.Sequential(*[Block(dim, heads) for _ in range(depth)])
        self.layer_norm = nn.LayerNorm(dim, eps=1e-5)  # unlike the blocks' 1e-6 (parity vectors)

    def forward(self, x: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
        """-> B x (1 + kept) x C; ``keep`` (B x kept token indices) or None for all tokens."""
        tokens = self.patchify(x) + self.pos_embedding.transpose(0, 1)  # B x T x C
        if keep is not None:
            tokens = torch.gather(tokens, 1, keep.unsqueeze(-1).expand(-1, -1, tokens.shape[-1]))
        tokens = torch.cat([self.cls_token.expand(tokens.shape[0], -1, -1), tokens], dim=1)
        return self.layer_norm(self.transformer(tokens))


class Decoder(nn.Module):
    def __init__(self, rows: int, sectors: int, dim: int, heads: int, depth: int) -> None:
        super().__init__()
        self.rows, self.tokens = rows, rows * sectors // 2
        self.mask_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embedding = nn.Parameter(torch.randn(self.tokens + 1, 1, dim) * 0.02)
        self.transformer = nn.Sequential(*[Block(dim, heads) for _ in range(depth)])
        self.head = nn.Linear(dim, 2)

    def forward(self, encoded: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
        """B x (1 + kept) x C -> B x R x S."""
        b, _, c = encoded.shape
        tokens = encoded[:, 1:]
        if keep is not None:  # scatter the kept tokens back, mask tokens elsewhere
            full = self.mask_token.expand(b, self.tokens, c).clone()
            full.scatter_(1, keep.unsqueeze(-1).expand(-1, -1, c), tokens)
            tokens = full
        x = torch.cat([encoded[:, :1], tokens], dim=1) + self.pos_embedding.transpose(0, 1)
        x = self.head(self.transformer(x)[:, 1:])  # B x T x 2: two adjacent sectors per token
        return x.reshape(b, self.rows, -1)


class SequenceModel(nn.Module):
    """B x K x 12 x 90 (query frame first) -> F_seq B x 12 x 90 in [0, 1].

    ``straight_through_clamp`` (a training option, not the release's): in training mode the
    output is still clamped to [0, 1], but gradients pass the clamp as if it were not there,
    so cells pushed out of [0, 1] can come back (with the plain clamp they never receive a
    gradient again; see lcpr_core.vseq2pc.training). Values, and so parity, are unchanged.
    """

    def __init__(
        self,
        *,
        frames: int = 4,
        rows: int = 12,
        sectors: int = 90,
        dim: int = 48,
        heads: int = 3,
        depth: int = 4,
        mask_ratio: float = 0.1,
        straight_through_clamp: bool = False,
    ) -> None:
        super().__init__()
        if sectors % 2:
            raise InvalidValueError(f"sectors={sectors}; it must be even (tokens cover two sectors)")
        if not 0 <= mask_ratio < 1:
            raise InvalidValueError(f"mask_ratio={mask_ratio}; it must be in [0, 1)")
        self.frames, self.rows, self.sectors, self.mask_ratio = frames, rows, sectors, mask_ratio
        self.straight_through_clamp = straight_through_clamp
        self.encoder = Encoder(frames, rows, sectors, dim, heads, depth)
        self.decoder = Decoder(rows, sectors, dim, heads, depth)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        want = (self.frames, self.rows, self.sectors)
        if frames.dim() != 4 or tuple(frames.shape[1:]) != want:
            raise InputShapeError(f"frames have shape {tuple(frames.shape)}; expected B x {' x '.join(map(str, want))}")
        keep = self._kept_tokens(frames.shape[0], frames.device) if self.training else None
        raw = self.decoder(self.encoder(frames, keep), keep)  # B x 12 x 90
        if self.training and self.straight_through_clamp:
            return raw + (raw.clamp(0, 1) - raw).detach()
        return raw.clamp(0, 1)

    def _kept_tokens(self, batch: int, device: torch.device) -> torch.Tensor | None:
        tokens = self.rows * self.sectors // 2
        kept = int(tokens * (1 - self.mask_ratio))
        if kept == tokens:
            return None
        return torch.rand(batch, tokens, device=device).argsort(dim=1)[:, :kept]

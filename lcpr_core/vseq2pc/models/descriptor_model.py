"""VSeq2PC descriptor model: RINet-style towers for scans and sequences, and a match score."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ...errors import InvalidValueError

PADDINGS = ("zeros", "circular")


class RIConv(nn.Module):
    """B x C_in x S -> B x C_out x S: pad 2 on the right of the sectors, conv k=3, BN, LeakyReLU."""

    def __init__(self, in_ch: int, out_ch: int, padding: str = "zeros") -> None:
        super().__init__()
        if padding not in PADDINGS:
            raise InvalidValueError(f"padding={padding!r}; accepted: {', '.join(PADDINGS)}")
        self.mode = "constant" if padding == "zeros" else "circular"
        self.conv = nn.Sequential(nn.Conv1d(in_ch, out_ch, 3), nn.BatchNorm1d(out_ch), nn.LeakyReLU(0.1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, (0, 2), mode=self.mode))


class RIAttention(nn.Module):
    """Channel gating: x * sigmoid(Linear(mean over sectors))."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.fc = nn.Sequential(nn.Linear(channels, channels), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # B x C x S
        return x * self.fc(x.mean(dim=2)).unsqueeze(-1)


class RIDownsampling(nn.Module):
    """B x C x S -> B x C x S/r: of the r sector phases, keep the one with the largest sum |x|."""

    def __init__(self, ratio: int) -> None:
        super().__init__()
        self.ratio = ratio

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        phases = torch.stack([x[..., i :: self.ratio] for i in range(self.ratio)], dim=1)  # B x r x C x S/r
        best = phases.abs().sum(dim=(2, 3)).argmax(dim=1)  # B
        return phases[torch.arange(x.shape[0], device=x.device), best]


def tower_stage(index: int, padding: str) -> nn.Sequential:
    """Stage ``index`` (1..6) of the RINet tower."""
    if index == 1:
        return nn.Sequential(
            RIAttention(12), RIConv(12, 12, padding), RIAttention(12), RIConv(12, 16, padding), RIAttention(16)
        )
    ratio, in_ch, out_ch = {2: (3, 16, 16), 3: (3, 16, 32), 4: (2, 32, 32), 5: (2, 32, 64), 6: (2, 64, 128)}[index]
    return nn.Sequential(RIDownsampling(ratio), RIConv(in_ch, out_ch, padding), RIAttention(out_ch))


STAGES = range(1, 7)


class DescriptorModel(nn.Module):
    """Scan slices and camera sequences -> 288-d descriptors; a pair -> probability of the same place."""

    def __init__(self, *, padding: str = "zeros", camera_sectors: int = 90, sectors: int = 360) -> None:
        super().__init__()
        self.pad = (sectors - camera_sectors) // 2
        for i in STAGES:
            setattr(self, f"conv{i}", tower_stage(i, padding))
        for i in STAGES:
            setattr(self, f"conv{i}_seq", tower_stage(i, padding))
        self.linear = nn.Sequential(nn.Linear(288, 128), nn.LeakyReLU(0.1), nn.Linear(128, 1))

    def _stages(self, suffix: str = "") -> list[nn.Module]:
        return [getattr(self, f"conv{i}{suffix}") for i in STAGES]

    def scan_descriptor(self, slices: torch.Tensor) -> torch.Tensor:
        """B x 12 x 360 -> B x 288: the sector mean of every stage's output, concatenated."""
        means, x = [], slices
        for stage in self._stages():
            x = stage(x)
            means.append(x.mean(dim=2))
        return torch.cat(means, dim=1)

    def sequence_descriptor(self, f_seq: torch.Tensor, f_img: torch.Tensor) -> torch.Tensor:
        """F_seq and the query frame's feature F_img (B x 12 x 90 each) -> B x 288.

        The residual stream (conv*_seq) reads F_seq - F_img; the base stream (conv*,
        shared with scans) reads F_img and adds the residual stream's output after
        every stage (:meth:`descriptors` with no scans).
        """
        no_scans = f_img.new_zeros(0, f_img.shape[1], 2 * self.pad + f_img.shape[2])
        return self.descriptors(f_seq, f_img, no_scans)[0]

    def descriptors(self, f_seq: torch.Tensor, f_img: torch.Tensor, slices: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Both kinds in one pass of the shared tower: (B x 288 sequence, M x 288 scan descriptors).

        Equal to :meth:`sequence_descriptor` and :meth:`scan_descriptor` in eval mode. In training mode the
        shared tower's batch norm then normalises sequences and scans with the statistics of both together,
        as its running statistics (what eval mode uses) do; called apart, each kind gets its own.
        """
        pad = (self.pad, self.pad)
        residual, base, scans = F.pad(f_seq - f_img, pad), F.pad(f_img, pad), slices  # B / B / M x 12 x 360
        seq_means, scan_means = [], []
        for stage, stage_seq in zip(self._stages(), self._stages("_seq"), strict=True):
            residual = stage_seq(residual)
            both = stage(torch.cat([base, scans]))  # (B + M) x C x S
            base, scans = both[: len(base)] + residual, both[len(base) :]
            seq_means.append(base.mean(dim=2))
            scan_means.append(scans.mean(dim=2))
        return torch.cat(seq_means, dim=1), torch.cat(scan_means, dim=1)

    def logit(self, d_seq: torch.Tensor, d_scan: torch.Tensor) -> torch.Tensor:
        """B x 288, B x 288 -> B logits (broadcasts over leading dimensions)."""
        return self.linear((d_seq - d_scan).abs()).squeeze(-1)

    def score(self, d_seq: torch.Tensor, d_scan: torch.Tensor) -> torch.Tensor:
        """-> B probabilities that the sequence and the scan slice show the same place."""
        return torch.sigmoid(self.logit(d_seq, d_scan))

"""The two VSeq2PC networks together: queries -> sequence descriptors, scans -> slice descriptors."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputShapeError
from ..fingerprint import tensors_id
from .checkpoint import load_descriptor_state_dict, load_sequence_state_dict
from .initialisation import seeded_models
from .models import DescriptorModel, SequenceModel
from .preprocess import CAMERA_SECTORS

__all__ = ["DESCRIPTOR_DIM", "SLICES", "Vseq2pcNet", "scan_slice_descriptors", "slice_tensor", "weights_id"]

DESCRIPTOR_DIM = 288
SLICES = 8


@dataclass
class Vseq2pcNet:
    """SequenceModel + DescriptorModel in eval mode on one device; every method runs without gradients.

    ``weights_id`` names the descriptor weights (a hash of their bytes): slice descriptors
    made with other weights are not comparable, and maps record it.
    """

    sequence: SequenceModel
    descriptor: DescriptorModel
    device: torch.device
    weights_id: str

    @classmethod
    def from_models(cls, sequence: SequenceModel, descriptor: DescriptorModel, *,
                    device: str | torch.device = "cpu") -> Vseq2pcNet:
        dev = torch.device(device)
        sequence, descriptor = sequence.to(dev).eval(), descriptor.to(dev).eval()
        return cls(sequence=sequence, descriptor=descriptor, device=dev, weights_id=weights_id(descriptor))

    @classmethod
    def from_files(cls, *, sequence: str | os.PathLike[str], descriptor: str | os.PathLike[str],
                   device: str | torch.device = "cpu") -> Vseq2pcNet:
        """Released files (pickled sequence module, ``{'state_dict'}`` descriptor) or this project's."""
        seq, desc = SequenceModel(), DescriptorModel()
        seq.load_state_dict(load_sequence_state_dict(sequence, model=seq))
        desc.load_state_dict(load_descriptor_state_dict(descriptor, model=desc))
        return cls.from_models(seq, desc, device=device)

    @classmethod
    def seeded(cls, seed: int = 0, *, device: str | torch.device = "cpu") -> Vseq2pcNet:
        """The seeded initialisation training starts from (untrained; for baselines and tests)."""
        seq, desc = seeded_models(seed)
        return cls.from_models(seq, desc, device=device)

    @torch.inference_mode()
    def query_descriptors(self, frames: np.ndarray | torch.Tensor, *, batch: int = 64) -> np.ndarray:
        """B x 4 x 12 x 90 camera-feature sequences (query frame first) -> B x 288 float32."""
        x = _as_tensor(frames, (4, 12, 90), "frames")
        out = [self.descriptor.sequence_descriptor(self.sequence(chunk), chunk[:, 0])
               for chunk in x.to(self.device).split(batch)]
        return _stack(out)

    @torch.inference_mode()
    def slice_descriptors(self, features: np.ndarray | torch.Tensor, *, batch: int = 64) -> np.ndarray:
        """N x 12 x 360 LiDAR structure features -> N x 8 x 288 float32 (slice s: window from sector 135 + 45 s)."""
        f = _as_tensor(features, (12, 360), "features")
        out = [scan_slice_descriptors(self.descriptor, chunk.to(self.device)) for chunk in f.split(batch)]
        return _stack(out, tail=(SLICES, DESCRIPTOR_DIM))


def slice_tensor(features: torch.Tensor) -> torch.Tensor:
    """n x C x 360 -> n x 8 x C x 360, as :func:`lcpr_core.vseq2pc.preprocess.lidar_slices` (batched torch):
    slice s holds sectors [135 + 45 s, 225 + 45 s) (mod 360) at 135..224, zeros elsewhere."""
    n, c, sectors = features.shape
    step = sectors // SLICES
    lo, hi = CAMERA_SECTORS.start, CAMERA_SECTORS.stop
    source = (torch.arange(lo, hi, device=features.device)[None, :]
              + step * torch.arange(SLICES, device=features.device)[:, None]) % sectors  # 8 x 90
    out = features.new_zeros(n, SLICES, c, sectors)
    out[..., lo:hi] = features[:, :, source].permute(0, 2, 1, 3)  # n x C x 8 x 90 -> n x 8 x C x 90
    return out


def scan_slice_descriptors(descriptor: DescriptorModel, features: torch.Tensor) -> torch.Tensor:
    """n x 12 x 360 structure features -> n x 8 x 288 slice descriptors (keeps gradients)."""
    n = features.shape[0]
    d = descriptor.scan_descriptor(slice_tensor(features).reshape(n * SLICES, *features.shape[1:]))
    return d.view(n, SLICES, -1)


def weights_id(descriptor: DescriptorModel) -> str:
    """A short hash of the descriptor model's parameters and buffers (name, dtype, shape, bytes)."""
    return tensors_id(descriptor.state_dict())


def _as_tensor(x: np.ndarray | torch.Tensor, tail: tuple[int, ...], what: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, np.float32) if not isinstance(x, torch.Tensor) else x, dtype=torch.float32)
    if t.dim() == len(tail):
        t = t[None]
    if t.dim() != len(tail) + 1 or tuple(t.shape[1:]) != tail:
        raise InputShapeError(f"{what} have shape {tuple(t.shape)}; expected B x {' x '.join(map(str, tail))}")
    return t.cpu()


def _stack(parts: list[torch.Tensor], tail: tuple[int, ...] = (DESCRIPTOR_DIM,)) -> np.ndarray:
    if not parts:
        return np.zeros((0, *tail), np.float32)
    return torch.cat(parts).float().cpu().numpy()

"""VSeq2PC training (``vseq2pc_train``), in the rooms of LCPR's :mod:`lcpr_core.lcpr.training`: config, data,
loss, schedule, loop (epochs and validation), files, plot, train (the run) and cli. See :mod:`.train`."""
from .cli import main
from .config import TrainConfig
from .data import TrainData, split
from .loss import pair_logits, place_loss, ranking_loss
from .schedule import lr_at
from .train import train

__all__ = ["TrainConfig", "TrainData", "lr_at", "main", "pair_logits", "place_loss", "ranking_loss", "split",
           "train"]

"""VSeq2PC training, in the rooms of LCPR's :mod:`lcpr_core.lcpr.training`: config, data, loss, schedule,
loop (epochs and validation), files, plot and train (the run). See :mod:`.train`; its command line,
``vseq2pc_train``, is :mod:`lcpr_offline.vseq2pc_train`."""
from .config import TrainConfig
from .data import TrainData, split
from .loss import pair_logits, place_loss, ranking_loss
from .schedule import lr_at
from .train import train

__all__ = ["TrainConfig", "TrainData", "lr_at", "pair_logits", "place_loss", "ranking_loss", "split",
           "train"]

"""VSeq2PC around the networks: released weights, retrieval, data caches, training and evaluation.

    from lcpr_core.vseq2pc import Vseq2pcNet, Vseq2pcMap, SequenceBuilder
    net = Vseq2pcNet.from_files(sequence="seq.pth", descriptor="desc.pth")   # or Vseq2pcNet.seeded(0)
    vmap = Vseq2pcMap(net)
    vmap.add_scan(points, labels, stamp=t, pose=world_T_lidar)         # the LiDAR database
    builder = SequenceBuilder()
    batch = builder.push(camera_feature_12x90, stamp=t, pose=world_T_base)   # None until 15 m on
    if batch is not None:
        matches = vmap.query(batch)          # per query: best scans first (SearchConfig: k, exclusion, prefilter)

Modules: detector (SequenceDetector: what vseq2pc_node runs), checkpoint (released files,
including the pickled sequence module, loaded without running code), net (the two models
together), retrieval (the scan database, search, npz files), sequence (online query
assembly), dataset (the feature cache; ``vseq2pc_cache`` reads one from a bag:
:mod:`lcpr_offline.vseq2pc_cache`), pairs (labels and pair sampling), initialisation (the training
initialisation), training/ (vseq2pc_train), evaluate (vseq2pc_eval).
"""
from .checkpoint import (
    load_descriptor_state_dict,
    load_sequence_state_dict,
    read_pickled_module_state_dict,
    save_descriptor_weights,
    save_sequence_weights,
)
from .net import Vseq2pcNet
from .retrieval import DATABASE_SCHEMA_VERSION, ScanDatabase, ScanMatch, SearchConfig, Vseq2pcMap
from .sequence import SequenceBatch, SequenceBuilder, SequenceConfig, sequence_table

__all__ = [
    "DATABASE_SCHEMA_VERSION", "ScanDatabase", "ScanMatch", "SearchConfig", "SequenceBatch", "SequenceBuilder",
    "SequenceConfig", "sequence_table",
    "Vseq2pcMap", "Vseq2pcNet", "load_descriptor_state_dict", "load_sequence_state_dict",
    "read_pickled_module_state_dict", "save_descriptor_weights", "save_sequence_weights",
]

"""vseq2pc_ros: the ROS 2 side of VSeq2PC (camera sequence -> LiDAR map place recognition).

The node (:mod:`vseq2pc_ros.node`, executable ``vseq2pc_node``, node name ``vseq2pc``)
builds a LiDAR scan map from a labelled PointCloud2 stream (or loads one), turns depth +
label images into camera features, assembles 5/10/15 m sequences and publishes
``~/loop_closure`` and ``~/candidates`` in lcpr_node's layouts. It reuses lcpr_ros's
parameter walker, worker design, diagnostics, odometry buffer and process handling.
"""

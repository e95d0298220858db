"""lcpr_ros: the ROS 2 side of the loop-closure detector.

The node (:mod:`lcpr_ros.node`, executable ``lcpr_node``) only declares parameters,
builds :class:`lcpr_core.detector.DetectorConfig`, converts messages and calls
:class:`lcpr_core.detector.LoopDetector`. The pure-Python parts (parameter walking,
synchronisation, the single-slot worker, statistics) import no ROS and are tested
without it. ``lcpr_replay`` (:mod:`lcpr_ros.replay`) publishes a rosbag2 over DDS.
"""

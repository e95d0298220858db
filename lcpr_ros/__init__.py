"""lcpr_ros: the ROS 2 side of the LCPR loop-closure detector.

The node (:mod:`lcpr_ros.node`, executable ``lcpr_node``) only declares parameters
(:mod:`lcpr_ros.params`), builds :class:`lcpr_core.detector.DetectorConfig`, takes
messages in through :mod:`ros_common.inputs`, converts its outputs (:mod:`lcpr_ros.outputs`, :mod:`lcpr_ros.markers`),
pairs the cameras with each cloud (:mod:`lcpr_ros.sync`) and calls
:class:`lcpr_core.detector.LoopDetector`. What it shares with vseq2pc_node (parameter
walking, QoS, poses, the worker, statistics, /diagnostics, the map file, the process) is
:mod:`ros_common`. ``lcpr_replay`` (:mod:`lcpr_ros.replay`) publishes a rosbag2 over DDS;
``lcpr_eval`` (:mod:`lcpr_ros.evaluate`) evaluates a bag offline with the node's settings;
``lcpr_demo`` (:mod:`lcpr_ros.demo`) replays a drive through the node and scores it.
"""

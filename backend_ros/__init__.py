"""backend_ros: the ROS 2 side of the pose-graph back end (:mod:`lcpr_core.backend`).

``lcpr_backend`` (:mod:`backend_ros.node`, node name ``lcpr_backend``) feeds
:class:`lcpr_core.backend.PoseGraphBackend` with any nav_msgs/Odometry and the verified rows of a
detector's ``~/candidates`` (read by column name with :mod:`ros_common.tables`, so it needs neither
detector's package) and publishes the corrected odometry, the graph's path and map -> odom; its
settings are :mod:`backend_ros.config`. ``lcpr_kiss_icp`` (:mod:`backend_ros.kiss_icp_node`, node name
``lcpr_kiss_icp``) turns a PointCloud2 into odometry with KISS-ICP. What they share with the detector
nodes (parameter walking, QoS, stamps, the worker, statistics, /diagnostics, the process) is
:mod:`ros_common`. docs/backend.md describes both nodes.
"""

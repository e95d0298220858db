"""ros_common: the ROS layer both nodes share (lcpr_node and vseq2pc_node).

Each node package (:mod:`lcpr_ros`, :mod:`vseq2pc_ros`) keeps its own parameters, output messages
and the adapter around its core detector; what both need lives here:
typed config <-> ROS parameters (:mod:`.params`, :mod:`.ros_params`, :mod:`.config`),
QoS (:mod:`.qos`), header stamps and odometry (:mod:`.stamps`, :mod:`.poses`), the
worker thread (:mod:`.worker`), statistics and /diagnostics (:mod:`.stats`,
:mod:`.diagnostics`), the map file at ``map.path`` (:mod:`.mapstore`), the process
around a node (:mod:`.process`), the candidate-table layout (:mod:`.tables`), the
intake of every message kind the nodes take (:mod:`.inputs`: one call per kind), the errors
(:mod:`.errors`) and a harness that drives a node over DDS (:mod:`.harness`). The modules without an rclpy import are
tested without ROS.
"""

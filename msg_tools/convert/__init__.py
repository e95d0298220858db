"""Dataset -> rosbag2 converters (nuScenes, KITTI odometry) and a bag-info command."""

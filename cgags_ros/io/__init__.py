"""ROS-free input and output: cloud files, rosbag2 bags and PointCloud2 decoding."""

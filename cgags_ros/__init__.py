"""cgags_ros: global point cloud registration for ROS 2.

The package is layered so that each layer imports only what it needs:

- ``cgags_ros.registration``: the ROS-free core (numpy/scipy only).
- ``cgags_ros.features``: the point-cloud front end (Open3D).
- ``cgags_ros.pipeline``: clouds in, result out; used by the node, the CLIs and benchmarks.
- ``cgags_ros.ros``: the only code that imports rclpy and message types.

Importing ``cgags_ros`` itself pulls in none of them.
"""

__version__ = "0.1.0"

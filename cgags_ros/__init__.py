"""
cgags_ros: global point cloud registration for ROS 2.

Layers, each importing only the ones below it (a test checks this)::

    tools -> ros -> engine -> calibration -> pipeline -> frontend, registration
          -> geometry, config, io

``registration`` is the ROS-free core (numpy/scipy only), ``frontend`` the Open3D front
end, ``pipeline`` the one path every tool and the node call, ``engine`` what the node
decides without ROS, ``ros`` the only code that imports rclpy and message types (the node's
wiring). Importing the package changes nothing in the process; the entry points set up
their threads (:func:`cgags_ros.parallel.quiet_idle_threads`).
"""

__version__ = '0.1.0'

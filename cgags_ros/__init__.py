"""
cgags_ros: global point cloud registration for ROS 2.

Layers, each importing only the ones below it (a test checks this)::

    tools -> ros -> pipeline -> frontend, registration -> geometry, config, io

``registration`` is the ROS-free core (numpy/scipy only), ``frontend`` the Open3D front
end, ``pipeline`` the one path every tool and the node call, ``ros`` the only code that
imports rclpy and message types.
"""

import os

__version__ = '0.1.0'

# The thread pools under the front end read these when their libraries load, so they are
# set here, before any submodule imports numpy or Open3D (a user's own value wins; a
# spawned registration process inherits them). OpenMP's idle threads spin by default and,
# on a loaded machine, each of ICP's short parallel loops then waits for a descheduled
# thread; OpenBLAS's workers likewise spin after each threaded call and take the CPU from
# Open3D. Passive waiting costs nothing measurable on an idle machine (docs/method.md).
os.environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE')
os.environ.setdefault('OPENBLAS_THREAD_TIMEOUT', '20')

"""
The command-line tools.

cgags-register, cgags-replay, cgags-relocalize, cgags-calibrate, cgags-tune, cgags-map,
cgags-demo.

Each runs the pipeline in its own process, so this package, imported before any of them
loads numpy or Open3D, makes their idle threads sleep instead of spin
(:func:`~cgags_ros.parallel.quiet_idle_threads`).
"""

from ..parallel import quiet_idle_threads

quiet_idle_threads()

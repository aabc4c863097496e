"""
Relocalization in a prior map: requests, and a pose confirmed over several scans.

- :mod:`.service_calls`: what ``~/relocalize`` and ``reinitialize_global_localization`` ask, and
  their one-line answers (the node's engine holds them).
- :mod:`.sequence`: the node's side of a relocalization over several scans (each scan's
  pose in odom, the verdict after each answer, the robot's odometry by stamp where tf2 is
  missing). Light: numpy and scipy.
- :mod:`.relocalizer` and :mod:`.hypotheses`: the :class:`~.relocalizer.Relocalizer` itself,
  which runs where the map's features are (the registration process, ``cgags-relocalize``).
"""

"""
The compiled functions of the front end (numba): FPFH and the descriptor matching.

They make the putative correspondences the core starts from (docs/method.md, "Input"),
each ``nogil`` over a range of rows that :func:`cgags_ros.parallel.run_chunks` splits over
threads:

- :mod:`.neighbours`: the neighbour search FPFH runs once for both passes: each point's
  ``max_nn`` nearest within the radius, on a grid of cells (:func:`radius_neighbours`, on
  the :class:`.GridArrays` of :class:`~cgags_ros.frontend.neighbours.NeighbourGrid`);
- :mod:`.fpfh`: Open3D's FPFH on those neighbour lists: the SPFH pass (:func:`spfh_pass`), then
  the FPFH pass (:func:`fpfh_pass`);
- :mod:`.descriptor_index`: the exact nearest neighbours in descriptor space: the k-means
  cells of the index (:func:`kmeans`, :func:`assign`), its search (:func:`search`), the
  mutual check's question "is this row the nearest?" (:func:`nearest_is`), and the
  distances matching ranks by (:func:`squared_pair_distances`).

Each function's argument types are declared once, in its decorator, from the aliases of
:mod:`cgags_ros.compiled_types` and the named tuples of :mod:`.types`; importing this
package compiles every function from that declaration, or loads it from numba's on-disk
cache (``cache=True``, as the core's :mod:`cgags_ros.registration.compiled`). The front end
imports it with FPFH and matching, so a process pays compilation once, before its first
registration, and never on a later call: other argument types raise a ``TypeError``
instead of compiling.
"""

from .descriptor_index import (assign, kmeans, nearest_is, search, squared_distances_to,
                               squared_pair_distances)
from .fpfh import fpfh_pass, spfh_pass
from .neighbours import radius_neighbours
from .types import GridArrays, IndexArrays, NeighbourLists

__all__ = [
    'GridArrays', 'IndexArrays', 'NeighbourLists', 'assign', 'fpfh_pass', 'kmeans',
    'nearest_is', 'radius_neighbours', 'search', 'spfh_pass', 'squared_distances_to',
    'squared_pair_distances']

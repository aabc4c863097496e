"""
The compiled functions of the core (numba): the loops of Algorithm 1's steps.

Which paper step each module implements (the numbering of :mod:`.cgags` and
docs/method.md):

- :mod:`.graph`: step 1, the compatibility graph (:func:`compatibility_words`; 4-DoF
  :func:`vertical_compatibility_words`) and its entry lists (:func:`neighbour_lists`);
  the common neighbourhoods the later steps count on its bit rows;
- :mod:`.sampling`: step 2, minimal compatible subsets (graph edge sampling
  :func:`draw_edges`, graph vertex sampling :func:`draw_triples`, the collinearity test
  :func:`usable_triangles`), and step 5, guided sampling (:func:`draw_guided` on the rows
  of K that each step-6 refresh builds, :func:`guided_rows`);
- :mod:`.scoring`: step 3, hypotheses (minimal fits :func:`fit_triples`, pre-screen
  :func:`prescreen_scores`, residuals for the scores :func:`residual_matrix`), and step 8,
  the final re-fit (:func:`fit_weighted`, :func:`point_residuals`);
- :mod:`.preferences`: step 4, the preference lists (:func:`merge_preferences`) and the
  intersection kernel K (:func:`preference_bits`, :func:`intersection_kernel`);
- :mod:`.inlier_edges`: step 7, stopping: the edges among the best model's inliers
  (:func:`later_member_counts`, :func:`later_member_pairs` on a :func:`member_mask`);
- :mod:`.bits`: the bit rows' word layout and the word operations every step inlines.

Each function's argument types are declared once, in its decorator, from the aliases of
:mod:`cgags_ros.compiled_types` and the named tuples of :mod:`.types`; importing this
package compiles every function from that declaration, or loads it from numba's on-disk
cache (``cache=True``: ``__pycache__`` next to the modules, ``NUMBA_CACHE_DIR`` when set, a
user cache directory where the package directory is read-only). The core imports it with
the search, so a process pays compilation once, before its first registration, and never
on a later call: other argument types raise a ``TypeError`` instead of compiling.
"""

from .graph import (columns, common_support, common_within, compatibility_words, length_rows,
                    neighbour_lists, or_transpose_blocks, sub_adjacency,
                    vertical_compatibility_words)
from .inlier_edges import later_member_counts, later_member_pairs, member_mask
from .preferences import intersection_kernel, merge_preferences, preference_bits
from .sampling import (COLLINEAR, complete_rows, draw_edges, draw_guided, draw_triples, EMPTY,
                       guided_rows, usable_triangles, VERTEX_PROPOSALS)
from .scoring import (fit_triples, fit_weighted, point_residuals, prescreen_scores,
                      residual_matrix)
from .types import Correspondences, GraphArrays, GuidedRows
from ...compiled_types import c_array

__all__ = [
    'COLLINEAR', 'EMPTY', 'VERTEX_PROPOSALS', 'Correspondences', 'GraphArrays', 'GuidedRows',
    'c_array', 'columns', 'common_support', 'common_within', 'complete_rows',
    'compatibility_words', 'draw_edges', 'draw_guided', 'draw_triples',
    'fit_triples', 'fit_weighted', 'guided_rows', 'intersection_kernel',
    'later_member_counts', 'later_member_pairs', 'length_rows', 'member_mask',
    'merge_preferences', 'neighbour_lists', 'or_transpose_blocks', 'point_residuals',
    'preference_bits', 'prescreen_scores', 'residual_matrix', 'sub_adjacency',
    'usable_triangles', 'vertical_compatibility_words']

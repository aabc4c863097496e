"""
Benchmarks of cgags_ros, each run from the repository root as ``python -m bench.<name>``.

They call the package as a user does (``register_clouds``, ``register_correspondences``,
the node and the CLIs) beside the baselines of :mod:`bench.baselines`, and write their
results under ``out/bench/`` unless ``--output`` says otherwise. :mod:`bench.common` holds
what they share (output paths, ``--set``, tables, plots), :mod:`bench.problems` the core
benchmark's problems, :mod:`bench.revision` an earlier revision's core, and
:mod:`bench.datasets` the benchmark data readers (3DMatch, calibration rigs,
``gt_pairs.txt``, synthetic correspondences), which the installed package does not ship.
The one-off studies behind the shipped defaults are :mod:`bench.studies`
(``python -m bench.studies.<name>``); no benchmark here imports them.
"""

from cgags_ros.parallel import quiet_idle_threads

# Time the pipeline as its users run it: the tools and the node make idle OpenMP and OpenBLAS
# threads sleep before numpy and Open3D load (docs/design.md), and so must every benchmark,
# which imports this package first.
quiet_idle_threads()

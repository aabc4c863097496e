"""Environment defaults for the thread pools under the front end, set when imported.

The libraries read these when they load, so ``features.frontend``, ``pipeline`` and the
node import this module before numpy; where numpy or Open3D were loaded earlier it is too
late (``pipeline.register_clouds`` then still keeps BLAS to one thread where threadpoolctl
is installed). A user's own value always wins. A spawned registration process inherits them.

- ``OMP_WAIT_POLICY=PASSIVE``: Open3D parallelises with OpenMP, whose idle threads spin by
  default: on a machine where other work holds a core, each of ICP's many short parallel
  loops then waits for a descheduled thread (measured: ICP 5x slower, up to 0.3 s).
  Passive waiting costs nothing measurable on an idle machine.
- ``OPENBLAS_THREAD_TIMEOUT=20``: OpenBLAS (numpy's BLAS) has the same habit: after a
  threaded call (the descriptor matching's matrix products) its workers spin for 2^28
  cycles (~0.1 s), i.e. through the rest of the pair and into the next one's FPFH, and on
  2 cores they take the CPU from Open3D (measured on a LiDAR pair: FPFH 68 -> 44 ms,
  normals 9 -> 6 ms, ICP 20 -> 13 ms with a 2^20-cycle spin, ~0.4 ms).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "20")

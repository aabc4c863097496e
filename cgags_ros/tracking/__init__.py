"""
A stream's scans: tracked from their predicted pose when the gates allow, else global.

:class:`~.tracker.Tracker` registers a stream's scans (the node in continuous mode,
``cgags-replay``); :mod:`.prediction` predicts and compares poses; what each path produced
is added up where the stream is reported (:class:`~cgags_ros.runtime.jobs.StreamCounts`).
``Tracker`` is imported on first use: it brings in the pipeline (Open3D), which the node's
own process (it only counts) never needs.
"""

import importlib
from typing import Any

__all__ = ['Tracker']


def __getattr__(name: str) -> Any:
    if name == 'Tracker':
        return importlib.import_module('.tracker', __name__).Tracker
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')

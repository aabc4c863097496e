"""
Starting registration: what a lifecycle node's configure transition waits for.

ROS-free. :func:`start_registration` returns once a pair can be registered at once: the
registration process (:class:`~cgags_ros.runtime.supervisor.Supervisor`) has
finished its warm-up (the pipeline imported, its numba code compiled or read from its
cache, one small registration) and, with ``map.file``, the map's features are prepared
where the pipeline runs (:class:`~.map_target.MapTarget`). Otherwise it raises
:class:`~.interface.StartFailed` with the reason and leaves nothing running, so that
configure fails and the node stays unconfigured.

Every wait is bounded when the pipeline runs in its own process (``runtime.registration_timeout``
> 0, the default): the warm-up by :data:`~cgags_ros.runtime.supervisor.WARM_UP_LIMIT_S`, the
map load by ``map.load_timeout``. In the node's own process (``runtime.registration_timeout`` 0,
and ``mode: calibrate``) a Python call cannot be interrupted: the import, the warm-up and the
map load end when they end.
"""

from __future__ import annotations

from typing import Callable

from .interface import MapCloud, StartFailed
from .map_target import MapTarget
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..runtime.jobs import Runner
from ..runtime.process import ChildSession, warm_up
from ..runtime.supervisor import Supervisor


def start_registration(pipeline_cfg: PipelineConfig, cfg: NodeConfig, in_process: bool,
                       map_target: MapTarget | None, log: Callable[[str, str], None],
                       runner: Runner | None = None) -> tuple[Runner, MapCloud | None]:
    """
    Start what registers pairs and wait until it can (see the module doc).

    :param in_process: run the pipeline in this process even if ``runtime.registration_timeout``
        asks for a registration process (the calibrate mode does).
    :param map_target: the map to load, or None.
    :param runner: what runs the jobs (a test's stand-in); None: started here.
    :returns: (what runs a job: a supervised process or a ``ChildSession`` of this process;
        the map as a target or None).
    :raises StartFailed: the process did not warm up (it died, failed or ran past its
        limit), the pipeline failed to load, or the map cannot be used; a runner started
        here is closed.
    """
    started: Runner | None = None
    try:
        if runner is None and cfg.runtime.registration_timeout > 0 and not in_process:
            process = Supervisor(cfg.runtime.registration_timeout)
            runner = started = process
            process.wait_ready()
        elif runner is None:  # import the pipeline (and Open3D) now, not with the first pair
            warm_up()
            runner = started = ChildSession()
        target = None if map_target is None else map_target.load(runner, pipeline_cfg, cfg, log)
    except BaseException as exc:  # noqa: BLE001 - even Ctrl-C leaves no process behind
        if started is not None:
            started.close()
        if isinstance(exc, StartFailed) or not isinstance(exc, Exception):
            raise
        reason = (str(exc) if isinstance(exc, CgagsError)
                  else f'the registration pipeline failed to load: {exc!r}')
        raise StartFailed(reason) from exc
    return runner, target

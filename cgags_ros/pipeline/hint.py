"""
A hint: where a scan's sensor is believed to be in a map; only the places it covers are searched.

:class:`Hint` is a position with a radius, in the map frame: given as such (``cgags-relocalize
--hint X Y Z R``), or from a pose with its covariance (:meth:`Hint.from_pose`: the node's
``~/hint``, RViz's "2D Pose Estimate", a GNSS-derived pose). A pose whose height variance is 0
while its horizontal ones are not is planar (what 2-D localizers and RViz send): its height
says nothing, and only the horizontal distance to a place counts. The places a hint covers are
:meth:`~.places.PlaceIndex.rank`'s to find.

Numpy only, light to import: the node's jobs carry a hint to the registration process.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InvalidInputError

HINT_SIGMAS = 3.0  # a pose hint covers this many standard deviations of its position


@dataclasses.dataclass(frozen=True)
class Hint:
    """
    Where the sensor is believed to be: within ``radius`` of ``position``.

    :ivar position: (3,) metres, in the map frame (the map file's coordinates).
    :ivar radius: metres, at least 0.
    :ivar planar: the height is unknown: only the distance in x and y counts.
    """

    position: np.ndarray
    radius: float
    planar: bool = False

    def __post_init__(self) -> None:
        """Check the position (finite (3,)) and the radius (finite, at least 0)."""
        position = np.asarray(self.position, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise InvalidInputError(f'a hint position is a finite (3,) vector, got {position}')
        if not np.isfinite(self.radius) or self.radius < 0:
            raise InvalidInputError(f'a hint radius is finite and at least 0, got {self.radius}')
        object.__setattr__(self, 'position', position)
        object.__setattr__(self, 'radius', float(self.radius))
        object.__setattr__(self, 'planar', bool(self.planar))

    @classmethod
    def from_pose(cls, pose: np.ndarray, covariance: np.ndarray) -> Hint:
        """
        Return the hint of a pose with its covariance (``initialpose``, a GNSS fix).

        :param pose: 4x4 pose in the map frame (its translation is the position, metres).
        :param covariance: 6x6 (or 36 values, row-major) in PoseWithCovariance order; its
            position block's largest standard deviation times ``HINT_SIGMAS`` is the radius.
            A z variance of 0 beside a nonzero x or y one makes the hint planar.
        :raises InvalidInputError: a pose that is not 4x4, a covariance that is not finite
            or whose position block has a negative variance.
        """
        pose = np.asarray(pose, dtype=np.float64)
        cov = np.asarray(covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
        if pose.shape != (4, 4) or not np.isfinite(cov).all():
            raise InvalidInputError('a pose hint is a 4x4 pose and a finite 6x6 covariance')
        if (np.diag(cov) < 0).any():
            raise InvalidInputError(f'a pose hint has a negative variance: {np.diag(cov)}')
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (cov + cov.T)).max(), 0.0)))
        planar = cov[2, 2] == 0 and (cov[0, 0] > 0 or cov[1, 1] > 0)
        return cls(pose[:3, 3], HINT_SIGMAS * sigma, planar)

"""
Why a result is not to be trusted, as a code a program can match and a message a user reads.

Every result (:class:`~cgags_ros.registration.RegistrationResult`, the pipeline's, the
calibration's) carries ``refusal``: None when it is valid, else a :class:`Refusal`. Every
typed error (:mod:`cgags_ros.errors`) carries a code too, so a pair that fails before a
result exists is refused in the same words. :mod:`cgags_ros.validity` decides the refusals
of an estimate; docs/refusals.md says what each code means and what a user does about it.
The values are stable snake_case strings: they appear in JSON, CSV, /diagnostics keys and
service answers.
"""

from __future__ import annotations

import dataclasses
import enum


class RefusalCode(enum.Enum):
    """The category of a refusal (docs/refusals.md, one section a code)."""

    # The input itself
    BAD_INPUT = 'bad_input'  # malformed arrays, messages or files
    BAD_CONFIG = 'bad_config'  # a setting out of range, or a map prepared with other ones
    TOO_FEW_POINTS = 'too_few_points'  # a cloud empty, or too small after downsampling
    # The correspondences and the core's estimate
    NO_CORRESPONDENCES = 'no_correspondences'  # too few (distinct) putative matches
    NO_ESTIMATE = 'no_estimate'  # no consistent subset of correspondences: no model at all
    FEW_INLIERS = 'few_inliers'  # the consensus is smaller than a minimum
    COLLINEAR = 'collinear'  # a cloud, the matches or the consensus is (nearly) a line
    CHANCE_LEVEL = 'chance_level'  # the consensus is no larger than chance gives
    AMBIGUOUS = 'ambiguous'  # a distinct pose is about as well supported
    # The refined estimate's geometry
    DEGENERATE_AXIS = 'degenerate_axis'  # the overlap leaves some motion unconstrained
    LOW_FITNESS = 'low_fitness'  # too few points meet the other cloud after alignment
    FREE_SPACE = 'free_space'  # the pose puts surfaces where a sensor saw free space
    NO_SHARED_SURFACE = 'no_shared_surface'  # the pose's clouds share too little surface
    TILT = 'tilt'  # 4-DoF: the clouds are not levelled
    FRAMES_DISAGREE = 'frames_disagree'  # calibration: the frames support different poses
    # The relocalizer over a few scans with odometry
    UNEXPLAINED = 'unexplained'  # no pose explains every scan (odometry or map contradict)
    MORE_SCANS = 'more_scans'  # fewer scans than a confirmation needs
    LOW_CONFIDENCE = 'low_confidence'  # the calibrated P(right) is below min_confidence
    UNCERTAIN = 'uncertain'  # the covariance's loosest sigma is too large to act on
    TRACKING_LOST = 'tracking_lost'  # a tracked pose jumped from its prediction or lost fit
    # The node and its services
    TIMEOUT = 'timeout'  # past runtime.registration_timeout (or map.load_timeout)
    PROCESS_CRASHED = 'process_crashed'  # the registration process died during the pair
    START_FAILED = 'start_failed'  # the registration process or the map is unusable
    STALE = 'stale'  # on demand: the latest scan is older than relocalization.max_scan_age
    NO_SCAN = 'no_scan'  # a relocalization request saw no scan before its timeout
    INACTIVE = 'inactive'  # the node is not active (lifecycle)
    UNCONFIGURED = 'unconfigured'  # the node is not configured (lifecycle)
    SHUTDOWN = 'shutdown'  # the node is shutting down
    IGNORED = 'ignored'  # calibrate mode: a pair after the end, or of other frames
    UNPAIRED = 'unpaired'  # pairing dropped the source (no target in time, a full queue)
    LOW_RATIO = 'low_ratio'  # initial pose: best/runner-up support below the minimum
    COOLDOWN = 'cooldown'  # initial pose: too soon after the last one
    MAX_AUTO = 'max_auto'  # initial pose: the automatic publishes are used up
    NO_EXTRINSIC = 'no_extrinsic'  # initial pose: base <- sensor is unknown
    NO_POSE = 'no_pose'  # live replay: the node published nothing and said nothing
    INTERNAL_ERROR = 'internal_error'  # a bug or an unexpected failure: see the log


@dataclasses.dataclass(frozen=True)
class Refusal:
    """
    Why a result must not be trusted.

    :ivar code: the category, for programs and tests.
    :ivar message: what was measured against which setting, and what to do, for users.
    """

    code: RefusalCode
    message: str

    def __str__(self) -> str:
        return f'{self.code.value}: {self.message}'

    def summary(self) -> dict[str, str]:
        """Return ``{'code': ..., 'message': ...}`` (the CLIs' JSON)."""
        return {'code': self.code.value, 'message': self.message}


class Judged:
    """A result with a ``refusal`` (None: valid), which ``valid`` and ``reason`` read."""

    refusal: Refusal | None

    @property
    def valid(self) -> bool:
        """Tell whether the result is to be trusted (no refusal)."""
        return self.refusal is None

    @property
    def reason(self) -> str:
        """Return the refusal's message ('' when valid)."""
        return '' if self.refusal is None else self.refusal.message


def summary(refusal: Refusal | None) -> dict[str, str] | None:
    """Return the JSON form of ``refusal``: code and message, or None when valid (``null``)."""
    return None if refusal is None else refusal.summary()

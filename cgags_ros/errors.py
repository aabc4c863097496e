"""
Typed errors. Every message says what was wrong and what the user can do about it.

Every error carries a :class:`~cgags_ros.refusal.RefusalCode` (``code``; its class's, or
one given where it is raised), so a pair that fails with an error is refused with a code
like a result that is not valid (``refusal``).
"""

from __future__ import annotations

from .refusal import Refusal, RefusalCode


class CgagsError(Exception):
    """Base class of every error raised by cgags_ros."""

    code = RefusalCode.INTERNAL_ERROR

    def __init__(self, *args: object, code: RefusalCode | None = None):
        super().__init__(*args)
        if code is not None:  # an instance attribute: pickled with the error
            self.code = code

    @property
    def refusal(self) -> Refusal:
        """Return the refusal this error stands for: its code and its message."""
        return Refusal(self.code, str(self))


class InvalidInputError(CgagsError, ValueError):
    """Input arrays or clouds are malformed (wrong shape, non-finite values, mismatched sizes)."""

    code = RefusalCode.BAD_INPUT


class EmptyCloudError(InvalidInputError):
    """A point cloud has no (finite) points left."""

    code = RefusalCode.TOO_FEW_POINTS


class DegenerateCorrespondencesError(CgagsError):
    """
    Correspondences cannot determine a rigid transform (too few, identical or collinear).

    ``code``: NO_CORRESPONDENCES, or COLLINEAR when they lie on a line.
    """

    code = RefusalCode.NO_CORRESPONDENCES


class InvalidConfigError(CgagsError, ValueError):
    """A configuration value is out of range or of the wrong type."""

    code = RefusalCode.BAD_CONFIG


class MalformedCloudError(InvalidInputError):
    """
    A PointCloud2 message cannot be decoded.

    Causes: missing x/y/z fields, inconsistent sizes or unsupported datatypes. The message
    names the field or size that is wrong.
    """


class BagError(CgagsError):
    """A rosbag2 file or directory cannot be read (missing, not a bag, unreadable storage)."""

    code = RefusalCode.BAD_INPUT


class BagTopicError(BagError, KeyError):
    """A requested topic is not in the bag; the message lists the topics that are."""

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0]) if self.args else ''

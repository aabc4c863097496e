"""Typed errors. Every message says what was wrong and what the user can do about it."""


class CgagsError(Exception):
    """Base class of every error raised by cgags_ros."""


class InvalidInputError(CgagsError, ValueError):
    """Input arrays or clouds are malformed (wrong shape, non-finite values, mismatched sizes)."""


class EmptyCloudError(InvalidInputError):
    """A point cloud has no (finite) points left."""


class DegenerateCorrespondencesError(CgagsError):
    """Correspondences cannot determine a rigid transform (too few, identical or collinear)."""


class InvalidConfigError(CgagsError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class MalformedCloudError(InvalidInputError):
    """
    A PointCloud2 message cannot be decoded.

    Causes: missing x/y/z fields, inconsistent sizes or unsupported datatypes. The message
    names the field or size that is wrong.
    """


class BagError(CgagsError):
    """A rosbag2 file or directory cannot be read (missing, not a bag, unreadable storage)."""


class BagTopicError(BagError, KeyError):
    """A requested topic is not in the bag; the message lists the topics that are."""

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0]) if self.args else ''

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

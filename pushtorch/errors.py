"""Errors raised by pushtorch: one base class, one subclass per kind of bad input.

Every check on user input raises a :class:`PushtorchError` subclass whose message names the
problem, so a caller never receives a NaN, a hang or a silently empty result instead.
"""

from __future__ import annotations


class PushtorchError(Exception):
    """Base class of every error pushtorch raises on purpose."""


class InvalidPointCloudError(PushtorchError, ValueError):
    """A point cloud is empty, too small for its neighbourhood, or holds NaN/inf values."""


class InvalidMeshError(PushtorchError, ValueError):
    """A mesh file is missing, unreadable, not a mesh, or degenerate."""


class InvalidPoseError(PushtorchError, ValueError):
    """A pose or quaternion has the wrong shape, is not unit length, or is not finite."""


class InvalidParameterError(PushtorchError, ValueError):
    """A scalar parameter (scale, dimension, bandwidth, count, ...) is out of its valid range."""


class SimulationError(PushtorchError, RuntimeError):
    """The physics simulation could not run or produced an unusable result."""


class RecordFormatError(PushtorchError, ValueError):
    """A push-record shard or a model file is corrupt, tampered with, or of another format version."""


class ModelError(PushtorchError, RuntimeError):
    """A model could not be built or applied (e.g. no kernel survives the cut-offs)."""


class IncompleteRunError(RecordFormatError):
    """A run's push records are unfinished: shards its manifest promises are missing (resume the run)."""


class FolderInUseError(PushtorchError, RuntimeError):
    """A shard folder is being written by another running process (it holds the folder's lock)."""


class UnsafeNameError(InvalidParameterError):
    """A name that becomes part of a file name could leave its folder or is not a plain file name."""


class MissingDependencyError(PushtorchError, ImportError):
    """A library pushtorch needs cannot be imported (e.g. a system library of open3d is missing)."""

"""Exception hierarchy shared by every stage and the pipeline."""


class CalibError(Exception):
    """Base class of every error fluorocal raises on purpose."""


class InputError(CalibError, ValueError):
    """Bad shape, dtype, range, parameter or file content."""


class ShapeError(InputError):
    """An array has the wrong shape."""


class EstimationError(CalibError, RuntimeError):
    """A fit diverged or was degenerate for the stage as a whole."""


class ArtifactError(CalibError, OSError):
    """An artifact is unreadable, corrupt or of an incompatible schema."""


class NotConvergedWarning(UserWarning):
    """An iteration stopped at its cap before its convergence test held: the result may be short of its accuracy."""

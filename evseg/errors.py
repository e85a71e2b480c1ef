"""Errors evseg reports to users.

Every error a user can cause (a broken file, a bad option, a calibration with a missing field)
is an :class:`EvsegError`; the CLI prints its message on one line and exits non-zero, and
``--debug`` shows the traceback. Anything else reaching the CLI is a bug in evseg.
"""


class EvsegError(Exception):
    """Base of all user-facing errors; the message names the file, field and position."""


class EventDataError(EvsegError, ValueError):
    """Event data violates the event model (unsorted time, coordinates off the sensor, ...)."""


class FormatError(EvsegError, ValueError):
    """A file is not what its format says: wrong magic, truncated, corrupt, unknown format."""


class CalibrationError(EvsegError, ValueError):
    """A calibration file is missing a field or has a field of the wrong shape."""


class ConfigError(EvsegError, ValueError):
    """A configuration (YAML preset or file) has an unknown key or a value of the wrong type."""


class ModelError(EvsegError, RuntimeError):
    """A normal-flow model file is missing, corrupt or incompatible."""


def yaml_problem(exc: Exception) -> str:
    """One line describing a YAML parse error: where (line, column) and what.

    PyYAML's own message spans several lines with a source excerpt; the CLI prints one line.
    """
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    problem = getattr(exc, "problem", None) or first_line
    return f"not valid YAML{where}: {problem}"

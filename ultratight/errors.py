"""Exception hierarchy.

Every user-facing problem (bad file, bad parameter, corrupt navigation data)
raises a subclass of :class:`UltratightError` whose message names the file or
field and what was expected.  The CLI prints such errors as one line and exits
non-zero; anything else is a bug and shows a traceback.
"""


class UltratightError(Exception):
    """Base class of errors caused by user input or data, not by bugs."""


class ConfigError(UltratightError, ValueError):
    """Impossible or inconsistent parameters (scenario fields, CLI flags)."""


class InputFileError(UltratightError, OSError):
    """A missing, unreadable, truncated or malformed input file."""


class FormatError(InputFileError):
    """Sample-format problems: unknown format name, size not a whole number of samples."""


class NavDataError(UltratightError, ValueError):
    """Corrupt or inconsistent navigation data (RINEX records, LNAV words)."""


class FilterError(UltratightError, ValueError):
    """Bad filter input: wrong shapes, non-finite values, non-PD covariance."""


class DivergenceError(UltratightError, RuntimeError):
    """A filter or tracking loop diverged and cannot continue."""


class OutputError(UltratightError, OSError):
    """An output cannot be written: full disk, read-only file system, no permission, size limit."""

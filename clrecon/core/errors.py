"""Errors a user can act on. The CLI prints them as one line (no traceback unless --debug)."""


class ClreconError(Exception):
    """Base class: an error whose message alone tells the user what to do."""


class SceneError(ClreconError, ValueError):
    """A scene file or value is invalid: the message names the key, the value and what is allowed."""


class OpenCLUnavailable(ClreconError, RuntimeError):
    """No usable OpenCL platform/device."""


class StoreError(ClreconError, IOError):
    """A projection or volume store is missing, incomplete or corrupt."""


class InputError(ClreconError, ValueError):
    """A measured input (projection series, breathing trace, ECG) is invalid: the message names the
    file, the tag or row, and what was expected."""

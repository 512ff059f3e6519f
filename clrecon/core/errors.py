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


def first_error_line(text) -> str:
    """The line of a compiler's or library's message that says what went wrong (``error`` lines
    first), for a one-line report; at most 300 characters."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower()]
    return (errors or lines or ["(no message)"])[0][:300]

"""One OpenCL program built from source with exactly the given options, and its log on failure.

Shared by the runtime's kernel builds (:mod:`clrecon.core.runtime`) and the driver probe
(:mod:`clrecon.core.driver_probe`). Not ``pyopencl.Program.build``: that adds its own ``-I``
option, which changes PoCL's cache key in every virtual environment (docs/kernels.md, "Kernel
builds").
"""

from __future__ import annotations

import warnings

#: pyopencl warns "Non-empty compiler output encountered" after every build whose log is not
#: empty, and both CPU drivers log remarks on success. The filter is installed once, at import,
#: for that one message (``PYOPENCL_COMPILER_OUTPUT=1`` still shows the logs themselves): a
#: ``warnings.catch_warnings`` around each build is not thread-safe (a run builds kernels in its
#: truth thread too), and the warning reached the demo's stderr through it.
warnings.filterwarnings("ignore", message="Non-empty compiler output encountered", category=UserWarning)


class BuildFailed(Exception):
    """The driver refused the source: ``error`` (the ``pyopencl`` error) and ``log`` (the build log, may be '')."""

    def __init__(self, error, log: str):
        super().__init__(str(error))
        self.error, self.log = error, log


def build_from_source(cl, context, device, src: str, opts: list[str]):
    """The unwrapped program (``cl._Program``) of ``src`` built for ``device`` with ``opts``.

    Raises :class:`BuildFailed` carrying the build log."""
    raw = cl._Program(context, src)
    try:
        raw.build(" ".join(opts).encode())
    except cl.Error as err:
        try:
            log = raw.get_build_info(device, cl.program_build_info.LOG)
        except cl.Error:
            log = ""
        raise BuildFailed(err, log) from err
    return raw

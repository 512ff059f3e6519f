"""The driver probe, run in a child process: can this OpenCL device build and run a small kernel?

``python -m clrecon.core.driver_probe PLATFORM_NAME DEVICE_INDEX`` builds ``kernels/probe.cl``
(default options: full-precision builtins), runs it on 4096 values (edge cases 0, 1e-30, 1,
1e6 included) and compares the result with :func:`probe_reference` (float64). It prints one JSON
line: ``{"ok": bool, "reason": str, "seconds": float}``. :mod:`clrecon.core.drivers` runs it in
a child so that a driver that aborts the process while compiling (PoCL 3.0 did on AVX-512 with
``vload16``) costs a verdict, not the run.

``CLRECON_PROBE_FAIL`` (comma list of platform-name substrings, case-insensitive) makes the probe
build fail on the platforms it names, through the driver's own compiler (an ``#error`` in the
source): how the tests exercise the fallback and the no-driver error on a machine where every
driver works.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from clrecon.core.cl_build import BuildFailed, build_from_source
from clrecon.core.errors import first_error_line
from clrecon.core.kernel_sources import load_source

#: Options of the probe build: none. Not the fast kernels' -cl-fast-relaxed-math: under it Intel's
#: runtime takes exp and atan2 of 2e-4 relative error (the OpenCL spec allows it), which the fast
#: kernels never call (they use arithmetic and their own atan polynomial, kernels/atan_poly.h).
PROBE_OPTIONS: tuple[str, ...] = ()
#: |cl - ref| <= RTOL |ref| + ATOL: the OpenCL spec's full-precision builtins are within 4 ulp of
#: float32 (5e-7 relative); measured 2.3e-7 on Intel's runtime and PoCL; 1e-5 leaves room for
#: rounding and none for wrong code.
RTOL, ATOL = 1e-5, 1e-6
N_VALUES = 4096  # a multiple of 16


def probe_inputs() -> np.ndarray:
    """The probe's inputs, float32 of shape (N_VALUES,): edge cases, then a ramp over [0, 50]."""
    x = np.linspace(0.0, 50.0, N_VALUES).astype(np.float32)
    x[:4] = (0.0, 1e-30, 1.0, 1e6)
    return x


def probe_reference(x: np.ndarray) -> np.ndarray:
    """float64 reference of ``kernels/probe.cl``: sqrt(x) + exp(-x) + log1p(x) + atan2(x, 1 + x)."""
    x = np.asarray(x, np.float64)
    return np.sqrt(x) + np.exp(-x) + np.log1p(x) + np.arctan2(x, 1.0 + x)


def forced_failure(platform_name: str, environ=os.environ) -> bool:
    """Whether ``CLRECON_PROBE_FAIL`` names ``platform_name`` (a substring, case-insensitive)."""
    names = [s.strip().lower() for s in environ.get("CLRECON_PROBE_FAIL", "").split(",") if s.strip()]
    return any(s in platform_name.lower() for s in names)


def run_probe(platform_name: str, device_index: int) -> dict:
    """Build and run the probe on one device of the platform named exactly ``platform_name``."""
    import pyopencl as cl

    plats = [p for p in cl.get_platforms() if p.name == platform_name]
    if not plats:
        return {"ok": False, "reason": f"platform {platform_name!r} not found in the child process"}
    dev = plats[0].get_devices()[device_index]
    return probe_on(cl.Context([dev]), dev, force_fail=forced_failure(platform_name))


def probe_on(ctx, dev, force_fail: bool = False) -> dict:
    """Build ``kernels/probe.cl`` in ``ctx`` for ``dev``, run it, compare with :func:`probe_reference`."""
    import pyopencl as cl

    t0 = time.perf_counter()
    opts = list(PROBE_OPTIONS) + (["-DCLRECON_PROBE_FORCE_FAIL"] if force_fail else [])
    try:
        raw = build_from_source(cl, ctx, dev, load_source("probe.cl"), opts)
    except BuildFailed as failed:
        return {"ok": False, "reason": f"the kernel build failed: {first_error_line(failed.log or failed.error)}"}
    prog = cl.Program(raw)
    queue = cl.CommandQueue(ctx)
    x = probe_inputs()
    mf = cl.mem_flags
    a = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    out_buf = cl.Buffer(ctx, mf.WRITE_ONLY, x.nbytes)
    prog.probe(queue, (N_VALUES // 16,), None, a, out_buf, np.int32(N_VALUES // 16))
    out = np.empty_like(x)
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    ref = probe_reference(x)
    err = np.abs(out.astype(np.float64) - ref)
    bad = ~(err <= RTOL * np.abs(ref) + ATOL)  # NaN counts as bad
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return {"ok": False, "reason": f"the kernel ran but computed wrong values ({int(bad.sum())} of {N_VALUES}; "
                                       f"x = {x[i]:g}: {out[i]:g}, expected {ref[i]:g})"}
    return {"ok": True, "reason": "builds and runs the probe kernel", "seconds": round(time.perf_counter() - t0, 3)}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        verdict = run_probe(argv[0], int(argv[1]))
    except Exception as e:  # noqa: BLE001 - any failure of a driver is a verdict, reported in one line
        verdict = {"ok": False, "reason": f"{type(e).__name__}: {first_error_line(e)}"}
    print(json.dumps(verdict), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

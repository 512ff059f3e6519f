"""The one OpenCL runtime everyone uses: device choice, program build and cache.

Device choice, in order: the ``device`` argument, the ``CLRECON_DEVICE`` environment
variable, then the PoCL CPU device (installed from PyPI with ``pyopencl[pocl]``).
``CLRECON_DEVICE`` is ``PLATFORM_SUBSTRING[:DEVICE_INDEX]`` matched case-insensitively
against platform names (e.g. ``portable``, ``nvidia:0``, ``oclgrind``).

Programs are built once per (context, file, defines) and kept; kernels are fetched once per
program. The ``.cl`` sources live in the top-level ``kernels/`` folder (``clrecon/kernels``
inside an installed wheel). ``#include "x.h"`` lines are expanded here, in Python, so the
source string handed to the driver changes whenever a header does: PoCL's on-disk build
cache (keyed on the source text and options, ``POCL_CACHE_DIR``) then rebuilds exactly when
needed, and PyOpenCL's own cache (skipped on PoCL) is not relied upon.
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
import warnings
from pathlib import Path

import numpy as np

from clrecon.core.errors import OpenCLUnavailable

_INSTALL_HINT = (
    "no OpenCL platform found. Install the PoCL CPU driver with "
    "`pip install 'pyopencl[pocl]'` (or `pip install pocl-binary-distribution`), "
    "or set CLRECON_DEVICE to a platform that is installed"
)


def kernel_dir() -> Path:
    """Folder holding the ``.cl`` sources, from a checkout or an installed wheel."""
    package = Path(__file__).resolve().parent.parent  # clrecon/
    for cand in (package / "kernels", package.parent / "kernels"):
        if cand.is_dir() and any(cand.glob("*.cl")):
            return cand
    raise FileNotFoundError(f"OpenCL kernel sources not found next to {package}")


_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.M)


def load_source(name: str, _seen: set | None = None) -> str:
    """Source of ``kernels/name`` with local ``#include "..."`` expanded (each header once)."""
    seen = set() if _seen is None else _seen
    path = kernel_dir() / name
    text = path.read_text()

    def sub(m):
        inc = m.group(1)
        if inc in seen:
            return ""
        seen.add(inc)
        return f"// ---- begin {inc}\n{load_source(inc, seen)}\n// ---- end {inc}\n"

    return _INCLUDE.sub(sub, text)


def _format_define(key: str, value) -> str:
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float):
        return f"-D{key}={value!r}f"
    return f"-D{key}={value}"


#: Alignment of :func:`aligned_empty` arrays (bytes): one page.
HOST_ALIGN_BYTES = 4096


def aligned_empty(shape, dtype=np.float32) -> np.ndarray:
    """Uninitialised C-contiguous host array whose data start on a page boundary.

    A page boundary satisfies any device's ``CL_DEVICE_MEM_BASE_ADDR_ALIGN`` (PoCL: 1024
    bits), so :meth:`Runtime.share_with_device` can hand the array to a CPU device without a
    copy (NumPy's own allocations start 16 bytes past one)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    raw = np.empty(nbytes + HOST_ALIGN_BYTES, np.uint8)
    off = (-raw.ctypes.data) % HOST_ALIGN_BYTES
    return raw[off:off + nbytes].view(dtype).reshape(shape)


class Runtime:
    """Owns a context, a queue and the programs built in that context."""

    def __init__(self, device_spec: str | None = None):
        import pyopencl as cl

        self.cl = cl
        spec = device_spec or os.environ.get("CLRECON_DEVICE", "")
        try:
            platforms = cl.get_platforms()
        except cl.Error:  # pragma: no cover - depends on the machine
            platforms = []
        if not platforms:
            raise OpenCLUnavailable(_INSTALL_HINT)
        self.device = self._pick(platforms, spec)
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self._programs: dict = {}
        self._kernels: dict = {}
        self._lock = threading.Lock()

    @staticmethod
    def _pick(platforms, spec: str):
        if spec:
            name, _, idx = spec.partition(":")
            for p in platforms:
                if name.lower() in p.name.lower():
                    devs = p.get_devices()
                    i = int(idx) if idx else 0
                    if not 0 <= i < len(devs):
                        raise OpenCLUnavailable(
                            f"CLRECON_DEVICE={spec!r}: platform {p.name!r} has devices 0..{len(devs) - 1}")
                    return devs[i]
            names = ", ".join(repr(p.name) for p in platforms)
            raise OpenCLUnavailable(f"CLRECON_DEVICE={spec!r} matches no OpenCL platform; installed: {names}")
        for p in platforms:  # default: PoCL CPU
            if "portable" in p.name.lower() or "pocl" in p.name.lower():
                return p.get_devices()[0]
        return platforms[0].get_devices()[0]

    @property
    def description(self) -> str:
        d = self.device
        return f"{d.platform.name} / {d.name} ({d.max_compute_units} compute units)"

    @property
    def max_alloc_bytes(self) -> int:
        """The largest single buffer the device allows (``CL_DEVICE_MAX_MEM_ALLOC_SIZE``, bytes)."""
        return int(self.device.max_mem_alloc_size)

    @property
    def is_cpu(self) -> bool:
        return bool(self.device.type & self.cl.device_type.CPU)

    def program(self, name: str, **defines):
        """Build ``kernels/name`` with ``-Dkey=value`` options, once per runtime."""
        key = (name, tuple(sorted(defines.items())))
        with self._lock:
            prog = self._programs.get(key)
            if prog is None:
                opts = ["-cl-fast-relaxed-math", "-cl-mad-enable"] if defines.pop("_fast", False) else []
                opts += [_format_define(k, v) for k, v in sorted(defines.items())]
                prog = self._build(name, load_source(name), opts)
                self._programs[key] = prog
            return prog

    def _build(self, name: str, src: str, opts: list[str]):
        """``src`` built with exactly ``opts``, as a ``pyopencl.Program``.

        Not ``pyopencl.Program.build``: that adds ``-I <site-packages>/pyopencl/cl`` (its own
        headers, which the kernels here do not include) to the options, and PoCL keys its kernel
        cache on the options, so every new virtual environment compiled every kernel again (a
        fresh clone's first run; measured in docs/algorithms.md, "Kernel builds"). With the
        options the sources' own, a build made once on a machine serves every checkout of the
        same sources."""
        cl = self.cl
        raw = cl._Program(self.context, src)  # the unwrapped program (pyopencl's public 1-argument form below)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # PyOpenCL's "build succeeded with warnings" chatter
            try:
                raw.build(" ".join(opts).encode())
            except cl.Error as err:
                try:
                    log = raw.get_build_info(self.device, cl.program_build_info.LOG)
                except cl.Error:
                    log = ""
                raise RuntimeError(f"kernels/{name}: the OpenCL build failed on {self.device.name!r} with "
                                   f"options {' '.join(opts) or '(none)'}: {err}\n{log}") from err
        return cl.Program(raw)

    def kernel(self, name: str, kernel_name: str, **defines):
        """Kernel object ``kernel_name`` from ``kernels/name``, fetched once and kept."""
        key = (name, kernel_name, tuple(sorted(defines.items())))
        k = self._kernels.get(key)
        if k is None:
            k = getattr(self.program(name, **defines), kernel_name)
            self._kernels[key] = k
        return k

    # -- buffers: convert at the boundary -------------------------------------------------
    def to_device(self, array, dtype=np.float32, name: str = "array"):
        """Read-only device buffer from a C-contiguous copy of ``array`` in ``dtype``."""
        a = np.asarray(array)
        if a.dtype.kind not in "fiub":
            raise TypeError(f"{name}: expected a numeric array, got dtype {a.dtype}")
        a = np.ascontiguousarray(a, dtype=dtype)
        if a.nbytes > self.max_alloc_bytes:
            raise MemoryError(f"{name}: one device buffer of {a.nbytes / 2**30:.2f} GiB is above the device's "
                              f"largest allocation ({self.max_alloc_bytes / 2**30:.2f} GiB, "
                              f"CL_DEVICE_MAX_MEM_ALLOC_SIZE of {self.device.name!r})")
        mf = self.cl.mem_flags
        if a.nbytes == 0:
            a = np.zeros(1, dtype)
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)

    def share_with_device(self, array: np.ndarray, name: str = "array", dtype=np.float32):
        """Read-only device buffer over ``array``'s own memory where the device can read it there.

        On a CPU device (PoCL: device memory *is* host memory) a C-contiguous array of
        ``dtype`` aligned to the device's base address alignment becomes a
        ``CL_MEM_USE_HOST_PTR`` buffer: no copy, and no fresh pages to touch (a
        ``COPY_HOST_PTR`` buffer of 1 GB costs 0.8-2.5 s to fill here, docs/algorithms.md
        "Rows read in place"). Anything else -- a GPU, another dtype, an unaligned or strided
        array -- gets the copy of :meth:`to_device`. The caller must neither write ``array``
        nor let it go while the buffer lives (the returned buffer keeps a reference to it)."""
        a = np.asarray(array)
        align = max(1, int(self.device.mem_base_addr_align) // 8)
        # too large for one buffer: to_device raises the MemoryError with its message
        if not (self.is_cpu and a.dtype == np.dtype(dtype) and a.flags.c_contiguous and a.nbytes > 0
                and a.ctypes.data % align == 0 and a.nbytes <= self.max_alloc_bytes):
            return self.to_device(a, dtype, name)
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=a)

    def empty(self, shape, dtype=np.float32):
        nbytes = max(int(np.prod(shape)) * np.dtype(dtype).itemsize, 1)
        return self.cl.Buffer(self.context, self.cl.mem_flags.READ_WRITE, nbytes)

    def from_device(self, buf, shape, dtype=np.float32, wait_for=None) -> np.ndarray:
        out = np.empty(shape, dtype)
        if out.size:
            self.cl.enqueue_copy(self.queue, out, buf, wait_for=wait_for)
        return out


_runtimes: dict = {}
_rt_lock = threading.Lock()
_thread = threading.local()


@contextlib.contextmanager
def thread_runtime(rt: Runtime):
    """Within the block, :func:`get_runtime` (no device spec) in *this thread* returns ``rt``.

    For a background thread that runs OpenCL beside the main thread (the truths beside the
    reconstruction, :mod:`clrecon.pipeline.executors.local`): it gets its own context, queue and
    kernel objects, because a kernel object's arguments (``clSetKernelArg``) are not safe to set
    from two threads at once. Every call that falls back to the default runtime then uses ``rt``.
    """
    prev = getattr(_thread, "rt", None)
    _thread.rt = rt
    try:
        yield rt
    finally:
        _thread.rt = prev


def get_runtime(device_spec: str | None = None) -> Runtime:
    """The process-wide runtime for a device spec (contexts cannot be pickled or forked).

    Inside :func:`thread_runtime` (and with no ``device_spec``): that thread's runtime.
    """
    local = getattr(_thread, "rt", None)
    if local is not None and device_spec is None:
        return local
    key = (os.getpid(), device_spec or os.environ.get("CLRECON_DEVICE", ""))
    with _rt_lock:
        rt = _runtimes.get(key)
        if rt is None:
            rt = Runtime(device_spec)
            _runtimes[key] = rt
        return rt

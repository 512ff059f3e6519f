"""The one OpenCL runtime everyone uses: device choice, program build and cache.

Device choice, in order: the ``device`` argument, the ``CLRECON_DEVICE`` environment variable,
then the first OpenCL CPU driver in :data:`clrecon.core.drivers.CPU_DRIVERS` order (Intel's CPU
runtime, then PoCL, both installed from PyPI with the package) that passes the driver probe
(:mod:`clrecon.core.drivers`, docs/drivers.md). ``CLRECON_DEVICE`` is
``PLATFORM_SUBSTRING[:DEVICE_INDEX]`` matched case-insensitively against platform names (e.g.
``intel``, ``portable``, ``nvidia:0``, ``oclgrind``); nothing is probed then.

Programs are built once per (context, file, defines) and kept; kernels are fetched once per
program. The sources come from :mod:`clrecon.core.kernel_sources` with their ``#include`` lines
expanded, so every on-disk cache keyed on the source text rebuilds exactly when a header
changes. Across processes: PoCL keeps its own build cache (keyed on source and options,
``POCL_CACHE_DIR``); for drivers without one (Intel's CPU runtime compiles every program again in
every process, about 1 s for ``interp.cl``) the runtime keeps the built binaries under
``<cache>/kernels/``, keyed on platform, driver version, device, options and source.
PyOpenCL's own cache is not relied upon.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading

import numpy as np

from clrecon.core import drivers
from clrecon.core.cache import default_cache_dir
from clrecon.core.cl_build import BuildFailed, build_from_source
from clrecon.core.errors import OpenCLUnavailable, first_error_line
from clrecon.core.kernel_sources import kernel_dir, load_source  # noqa: F401 - kernel_dir re-exported

_INSTALL_HINT = (
    "no OpenCL platform found. Install the drivers that come with clrecon "
    "(`pip install --force-reinstall clrecon`: Intel's CPU runtime on x86-64 Linux and "
    "`pyopencl[pocl]`), or set CLRECON_DEVICE to a platform that is installed"
)


def _format_define(key: str, value) -> str:
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float):
        return f"-D{key}={value!r}f"
    return f"-D{key}={value}"


#: Alignment of :func:`aligned_empty` arrays (bytes): one page.
HOST_ALIGN_BYTES = 4096


def _aligned(shape, dtype, alloc) -> np.ndarray:
    """A page-aligned C-contiguous array of ``shape`` and ``dtype`` inside ``alloc(n, uint8)``."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    raw = alloc(nbytes + HOST_ALIGN_BYTES, np.uint8)
    off = (-raw.ctypes.data) % HOST_ALIGN_BYTES
    return raw[off:off + nbytes].view(dtype).reshape(shape)


def aligned_empty(shape, dtype=np.float32) -> np.ndarray:
    """Uninitialised C-contiguous host array whose data start on a page boundary.

    A page boundary satisfies any device's ``CL_DEVICE_MEM_BASE_ADDR_ALIGN`` (PoCL: 1024
    bits), so :meth:`Runtime.share_with_device` can hand the array to a CPU device without a
    copy (NumPy's own allocations start 16 bytes past one)."""
    return _aligned(shape, dtype, np.empty)


def aligned_zeros(shape, dtype=np.float32) -> np.ndarray:
    """Zero-filled :func:`aligned_empty`: NumPy's ``zeros`` (``calloc``), so a large array's pages
    become resident only where they are written (a ``fill(0)`` would touch every page at once)."""
    return _aligned(shape, dtype, np.zeros)


class KernelBuildError(OpenCLUnavailable):
    """A kernel file the chosen driver cannot build: one line naming file, device, options and the
    compiler's first error, and where to turn; the whole build log in ``.log``."""

    def __init__(self, name: str, rt: Runtime, opts: list[str], err, log: str):
        self.log = log
        first = first_error_line(log or str(err))
        others = [d.key for d in drivers.CPU_DRIVERS if not d.matches(rt.device.platform.name)]
        super().__init__(
            f"kernels/{name}: the OpenCL build failed on {rt.device.name!r} ({rt.device.platform.name} "
            f"{rt.device.driver_version}) with options {' '.join(opts) or '(none)'}: {first}; another driver may "
            f"build it: CLRECON_DEVICE={others[0] if others else 'NAME'} (`python -m clrecon devices` lists them; "
            f"--debug shows the build log)")


class Runtime:
    """Owns a context, a queue and the programs built in that context."""

    def __init__(self, device_spec: str | None = None):
        import pyopencl as cl

        self.cl = cl
        spec = device_spec or os.environ.get("CLRECON_DEVICE", "")
        registration = drivers.register_wheel_drivers()  # before the first platform query
        try:
            platforms = cl.get_platforms()
        except cl.Error:  # pragma: no cover - depends on the machine
            platforms = []
        if not platforms:
            raise OpenCLUnavailable(_INSTALL_HINT)
        if spec:
            how = f"CLRECON_DEVICE={spec}" if not device_spec else f"device {spec!r} asked for"
            self.choice = drivers.Choice(self._pick(platforms, spec), how, [], registration)
        else:
            self.choice = drivers.choose_cpu_device(platforms)
        self.device = self.choice.device
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self._programs: dict = {}
        self._kernels: dict = {}
        self._lock = threading.Lock()

    @staticmethod
    def _pick(platforms, spec: str):
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

    @property
    def driver(self) -> dict:
        """Platform, driver version, device and how it was chosen (results.json ``driver``)."""
        return self.choice.as_dict()

    @property
    def cache_tag(self) -> str:
        """This driver's part of cache keys: ``""`` for PoCL (the driver every existing cache was made
        with, so those stay valid), else ``"<platform> <driver version>"``. Projections, truths and
        kernel binaries of two drivers differ in their last bits, so each driver keeps its own."""
        p = self.device.platform
        return "" if drivers.POCL.matches(p.name) else f"{p.name} {self.device.driver_version}"

    @property
    def description(self) -> str:
        d = self.device
        return f"{d.platform.name} {d.driver_version} / {d.name} ({d.max_compute_units} compute units)"

    @property
    def max_alloc_bytes(self) -> int:
        """The largest single buffer the device allows (``CL_DEVICE_MAX_MEM_ALLOC_SIZE``, bytes)."""
        return int(self.device.max_mem_alloc_size)

    @property
    def is_cpu(self) -> bool:
        return bool(self.device.type & self.cl.device_type.CPU)

    @property
    def is_oclgrind(self) -> bool:
        """Whether the device is Oclgrind's simulator (the suite's kernel checker)."""
        return "oclgrind" in self.device.platform.name.lower()

    def program(self, name: str, **defines):
        """Build ``kernels/name`` with ``-Dkey=value`` options, once per runtime. ``_fast``: relaxed
        math; ``_folder``: a folder of kernels outside the package to look in first (a study's:
        :func:`clrecon.core.kernel_sources.load_source`)."""
        key = (name, tuple(sorted(defines.items())))
        with self._lock:
            prog = self._programs.get(key)
            if prog is None:
                opts = ["-cl-fast-relaxed-math", "-cl-mad-enable"] if defines.pop("_fast", False) else []
                folder = defines.pop("_folder", None)
                opts += [_format_define(k, v) for k, v in sorted(defines.items())]
                prog = self._build(name, load_source(name, folder=folder), opts)
                self._programs[key] = prog
            return prog

    def _build(self, name: str, src: str, opts: list[str]):
        """``src`` built with exactly ``opts``, as a ``pyopencl.Program``.

        Not ``pyopencl.Program.build``: that adds ``-I <site-packages>/pyopencl/cl`` (its own
        headers, which the kernels here do not include) to the options, and PoCL keys its kernel
        cache on the options, so every new virtual environment compiled every kernel again (a
        fresh clone's first run; measured in docs/kernels.md, "Kernel builds"). With the
        options the sources' own, a build made once on a machine serves every checkout of the
        same sources."""
        cl = self.cl
        cached = self._binary_path(src, opts)
        if cached is not None and cached.is_file():
            try:
                raw = cl._Program(self.context, [self.device], [cached.read_bytes()])
                raw.build(" ".join(opts).encode())  # the compiler-output warning: filtered in cl_build
                return cl.Program(raw)
            except (cl.Error, OSError):  # a binary of another driver build, or damaged: build from source
                cached.unlink(missing_ok=True)
        try:
            raw = build_from_source(cl, self.context, self.device, src, opts)
        except BuildFailed as failed:
            raise KernelBuildError(name, self, opts, failed.error, failed.log) from failed.error
        if cached is not None:
            self._keep_binary(raw, cached)
        return cl.Program(raw)

    def _binary_path(self, src: str, opts: list[str]):
        """Where this program's binary is kept, or None where the driver keeps its own cache (PoCL)."""
        p = self.device.platform
        if drivers.POCL.matches(p.name) or self.is_oclgrind:
            return None
        key = "\0".join([p.name, p.version, self.device.name, self.device.driver_version, " ".join(opts), src])
        return default_cache_dir() / "kernels" / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.bin"

    def _keep_binary(self, raw, path) -> None:
        """Write the built program's binary to ``path`` (temporary name, then rename); a failure costs
        only the next process's build."""
        try:
            binary = raw.get_info(self.cl.program_info.BINARIES)[0]
            if not binary:
                return
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
            tmp.write_bytes(bytes(binary))
            os.replace(tmp, path)
        except (self.cl.Error, OSError):
            pass

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
        ``COPY_HOST_PTR`` buffer of 1 GB costs 0.8-2.5 s to fill here, docs/kernels.md
        "Rows read in place"). Anything else -- a GPU, another dtype, an unaligned or strided
        array -- gets the copy of :meth:`to_device`; so does Oclgrind, whose uninitialised-value
        plugin takes memory handed to it in place for unwritten (it reports every read of it). The
        caller must neither write ``array`` nor let it go while the buffer lives (the returned
        buffer keeps a reference to it)."""
        a = np.asarray(array)
        align = max(1, int(self.device.mem_base_addr_align) // 8)
        # too large for one buffer: to_device raises the MemoryError with its message
        if not (self.is_cpu and not self.is_oclgrind and a.dtype == np.dtype(dtype) and a.flags.c_contiguous
                and a.nbytes > 0 and a.ctypes.data % align == 0 and a.nbytes <= self.max_alloc_bytes):
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
    key = (os.getpid(), device_spec or os.environ.get("CLRECON_DEVICE", ""), drivers.preferred())
    with _rt_lock:
        rt = _runtimes.get(key)
        if rt is None:
            rt = Runtime(device_spec)
            _runtimes[key] = rt
        return rt


def default_cache_tag() -> str:
    """:attr:`Runtime.cache_tag` of the default runtime (``get_runtime()``): the driver's part of the keys
    of the projection stores and the truth cache."""
    return get_runtime().cache_tag

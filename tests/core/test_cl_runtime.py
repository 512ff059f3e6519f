"""The OpenCL runtime: kernel sources found, headers expanded, programs built once."""

import numpy as np
import pytest

from clrecon.core import kernel_sources
from clrecon.core import runtime as cl_runtime
from clrecon.core.errors import OpenCLUnavailable


def test_kernel_dir_has_sources():
    d = kernel_sources.kernel_dir()
    assert any(d.glob("*.cl"))


def test_include_expansion(tmp_path, monkeypatch):
    (tmp_path / "a.h").write_text("#define A 3\n")
    (tmp_path / "k.cl").write_text('#include "a.h"\n#include "a.h"\n__kernel void f(__global int*x){x[0]=A;}\n')
    (tmp_path / "k2.cl").write_text('#include "a.h"\n__kernel void f(__global int*x){x[0]=A+1;}\n')
    rt, rt2 = cl_runtime.Runtime(), cl_runtime.Runtime()  # (their driver probe reads kernels/probe.cl)
    monkeypatch.setattr(kernel_sources, "kernel_dir", lambda: tmp_path)
    src = kernel_sources.load_source("k.cl")
    assert src.count("#define A 3") == 1 and "#include" not in src
    prog = rt.program("k.cl")
    assert rt.program("k.cl") is prog  # built once
    buf = rt.empty((1,), np.int32)
    rt.kernel("k.cl", "f")(rt.queue, (1,), None, buf)
    assert rt.from_device(buf, (1,), np.int32)[0] == 3
    # editing the header changes the source handed to the driver -> rebuilt with the new value
    (tmp_path / "a.h").write_text("#define A 5\n")
    rt2.kernel("k2.cl", "f")(rt2.queue, (1,), None, buf2 := rt2.empty((1,), np.int32))
    assert rt2.from_device(buf2, (1,), np.int32)[0] == 6


def test_default_device_is_a_cpu_driver_that_passed_the_probe():
    """Without CLRECON_DEVICE the runtime takes the first CPU driver in clrecon's order that passes the
    probe (tests/core/test_drivers.py tests the order and the fallback); with it, exactly that platform."""
    rt = cl_runtime.get_runtime()
    assert rt.is_cpu
    assert cl_runtime.get_runtime() is rt
    if not rt.driver["chosen_by"].startswith("CLRECON_DEVICE"):
        assert rt.driver["probes"] and rt.driver["probes"][-1]["ok"]
        assert rt.driver["probes"][-1]["platform"] == rt.device.platform.name


def test_bad_device_spec_names_installed_platforms():
    with pytest.raises(OpenCLUnavailable, match="matches no OpenCL platform; installed"):
        cl_runtime.Runtime("no-such-platform-xyz")


def test_no_platform_says_what_to_install(monkeypatch):
    import pyopencl as cl
    monkeypatch.setattr(cl, "get_platforms", lambda: [])
    with pytest.raises(OpenCLUnavailable, match=r"no OpenCL platform found.*pip install --force-reinstall clrecon"):
        cl_runtime.Runtime()


def test_to_device_rejects_non_numeric():
    rt = cl_runtime.get_runtime()
    with pytest.raises(TypeError, match="numeric"):
        rt.to_device(np.array(["a"]))


def test_programs_are_built_with_their_own_options_only():
    """PoCL keys its on-disk kernel cache on the build options: they must not carry a path of the
    virtual environment (pyopencl.Program.build adds -I <site-packages>/pyopencl/cl), or every new
    venv compiles every kernel again (docs/kernels.md, "Kernel builds")."""
    rt = cl_runtime.get_runtime()
    prog = rt.program("ssrb.cl")
    opts = prog.get_build_info(rt.device, rt.cl.program_build_info.OPTIONS)
    assert "pyopencl" not in opts and "site-packages" not in opts, opts
    knl = rt.kernel("interp.cl", "apply_weights_interleaved16_cols8", APPLY_K=2)
    assert knl.function_name == "apply_weights_interleaved16_cols8"
    opts = knl.program.get_build_info(rt.device, rt.cl.program_build_info.OPTIONS)
    assert opts.split() == ["-DAPPLY_K=2"], opts


def test_a_failed_build_names_the_file_the_device_and_the_options():
    rt = cl_runtime.get_runtime()
    want = r"kernels/broken\.cl: the OpenCL build failed on .* with options -DX=1"
    with pytest.raises(RuntimeError, match=want) as e:
        rt._build("broken.cl", "__kernel void k(__global float *a) { a[0] = undeclared_name; }", ["-DX=1"])
    msg = str(e.value)
    assert "\n" not in msg and "undeclared_name" in msg and "CLRECON_DEVICE=" in msg  # one line, the cause, a remedy
    assert "undeclared_name" in e.value.log


@pytest.mark.parametrize("shape", [(0,), (3,), (7, 5), (300, 13, 240)])
def test_aligned_arrays_start_on_a_page_and_zeros_are_zero(shape):
    """``aligned_empty`` and ``aligned_zeros`` (what a CPU device reads in place) start on a page
    boundary, C-contiguous, of the asked shape and dtype; ``aligned_zeros`` holds zeros."""
    for make in (cl_runtime.aligned_empty, cl_runtime.aligned_zeros):
        a = make(shape, np.float32)
        assert a.shape == shape and a.dtype == np.float32 and a.flags.c_contiguous and a.flags.writeable
        assert a.size == 0 or a.ctypes.data % cl_runtime.HOST_ALIGN_BYTES == 0
    z = cl_runtime.aligned_zeros(shape, np.float64)
    assert z.dtype == np.float64 and not z.any()

"""Exit 0 where PoCL passes clrecon's driver probe on this CPU; else print why not (one line) and exit 1.

.ci/run runs the kernel and numerics tests a second time on PoCL only where this passes
(docs/drivers.md "The suite on both drivers")."""

import sys

import pyopencl as cl

from clrecon.core import drivers

drivers.register_wheel_drivers()
names = [p.name for p in cl.get_platforms() if drivers.POCL.matches(p.name)]
if not names:
    print(f"PoCL is not installed here ({drivers.POCL.package})")
    sys.exit(1)
ok, reason = drivers.run_probe_child(names[0], 0)
if not ok:
    print(f"PoCL does not pass the probe on this CPU, {drivers.cpu_line()}: {reason}")
    sys.exit(1)
sys.exit(0)

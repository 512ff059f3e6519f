"""The command line every benchmark of this folder shares: ``--quick``, ``--repeats``, ``--json``
(and ``--only`` where a benchmark has rows); prints its report lines and the machine's load."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from clrecon.bench import suite


def main(bench, report_lines, rows=None, argv=None) -> int:
    """Run ``bench(quick=..., repeats=..., [only=...])`` and print ``report_lines(result)``."""
    p = argparse.ArgumentParser(description=(bench.__doc__ or "").strip().splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smaller sizes (minutes)")
    p.add_argument("--repeats", type=int, default=3, help="alternating repeats per row (medians)")
    p.add_argument("--json", help="also write every number and the machine here")
    if rows:
        p.add_argument("--only", help="comma list from " + ",".join(rows))
    a = p.parse_args(argv)
    kw = {"only": tuple(x.strip() for x in a.only.split(","))} if rows and a.only else {}
    load0 = os.getloadavg()[0]
    res = bench(quick=a.quick, repeats=a.repeats, **kw)
    print("\n".join(report_lines(res)))
    print(f"load (1 min): {load0:.2f} -> {os.getloadavg()[0]:.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps({"machine": suite.machine(), "result": res}, indent=1,
                                           default=suite._json_default))
    return 0

"""The motion-model study's own modules (``benchmarks/studies/motion-model/``, outside the wheel),
importable by the tests: the study's scripts put their folder first on ``sys.path`` and import
them by name (``import correction``), and so does this module.

``correction``: the model-based correction variant (B); ``warp``: its OpenCL warp
(``mc_warp.cl`` there); ``demons``: ITK's demons as a plugged-in registration;
``registration_memory``: one Lucas-Kanade registration's peak in a spawned worker.
"""

import sys
from pathlib import Path

FOLDER = Path(__file__).resolve().parents[2] / "benchmarks" / "studies" / "motion-model"
if str(FOLDER) not in sys.path:
    sys.path.insert(0, str(FOLDER))

import correction  # noqa: E402
import demons  # noqa: E402
import registration_memory  # noqa: E402
import warp  # noqa: E402

__all__ = ["FOLDER", "correction", "demons", "registration_memory", "warp"]

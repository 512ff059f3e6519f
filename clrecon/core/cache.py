"""Where clrecon keeps what it can make again: projection stores, truths, kernel binaries, driver verdicts."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """``$CLRECON_CACHE`` if set, else ``~/.cache/clrecon``."""
    env = os.environ.get("CLRECON_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "clrecon"

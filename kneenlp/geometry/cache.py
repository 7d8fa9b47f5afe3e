"""Where kneenlp keeps what it builds once per machine: the femoral distance fields
(:func:`kneenlp.geometry.sdf.cached_field`) and the compiled contact loops (numba's cache,
:mod:`kneenlp.geometry.kernels`): ``$KNEENLP_CACHE``, else ``$XDG_CACHE_HOME/kneenlp``, else
``~/.cache/kneenlp``; never the package's own directory.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir(*parts: str) -> Path | None:
    """The cache directory (or its subdirectory ``parts``), created if needed; ``None`` if it
    cannot be created or written (the callers then build every time)."""
    env = os.environ.get("KNEENLP_CACHE")
    base = Path(env) if env else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "kneenlp"
    base = base.joinpath(*parts)
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return base if os.access(base, os.W_OK) else None

"""Where kneenlp keeps what it builds once per machine: the femoral distance fields
(:func:`kneenlp.geometry.sdf.cached_field`) and the compiled contact loops (numba's cache,
:mod:`kneenlp.geometry.kernels`): ``$KNEENLP_CACHE``, else the platform's user cache directory
(:func:`platformdirs.user_cache_dir`: ``$XDG_CACHE_HOME/kneenlp`` or ``~/.cache/kneenlp`` on Linux,
``~/Library/Caches/kneenlp`` on macOS, ``%LOCALAPPDATA%\\kneenlp\\Cache`` on Windows); never the
package's own directory.
"""

from __future__ import annotations

import os
from pathlib import Path

from platformdirs import user_cache_dir


def cache_dir(*parts: str) -> Path | None:
    """The cache directory (or its subdirectory ``parts``), created if needed; ``None`` if it
    cannot be created or written (the callers then build every time)."""
    env = os.environ.get("KNEENLP_CACHE")
    base = Path(env) if env else Path(user_cache_dir("kneenlp", appauthor=False))
    base = base.joinpath(*parts)
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return base if os.access(base, os.W_OK) else None

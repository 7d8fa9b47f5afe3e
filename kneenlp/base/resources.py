"""Data shipped inside the package (``kneenlp/resources/``), read through ``importlib.resources``.

The tree holds the default knee (``knees/default``), parameter sets (``parameters``), the paper's
protocols (``protocols``), example datasets (``datasets``) and the paper's published numbers
(``paper``).  It is installed with the package (wheel or editable), so nothing depends on the
current directory or on a source checkout.  User files are always given by path instead.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def resource(*parts: str) -> Path:
    """Path of a shipped resource, e.g. ``resource("protocols", "set1.toml")``.

    Installed packages are plain directories (wheels are unpacked), so the traversable is a real
    file-system path that trimesh, pandas and ``open`` can read.
    """
    return Path(str(files("kneenlp").joinpath("resources", *parts)))


def shipped_knees() -> list[str]:
    """Names of the knees shipped with the package (``knees/<name>/knee.toml``)."""
    return sorted(p.parent.name for p in resource("knees").glob("*/knee.toml"))

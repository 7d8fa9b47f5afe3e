"""JSON output helpers."""

from __future__ import annotations

import json

import numpy as np


def json_safe(value):
    """Nested dicts/lists with numpy scalars and non-finite floats made JSON-safe (NaN/inf -> null)."""
    if isinstance(value, dict):
        return {k: json_safe(x) for k, x in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(x) for x in value]
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    return value


def dumps(value) -> str:
    return json.dumps(json_safe(value), indent=2)

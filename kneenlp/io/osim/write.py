"""Writing OpenSim models: a calibrated copy (only the given ligament properties changed, edited
as text inside the XML) and a copy the plain ``opensim`` package can load (OpenSim JAM-only
classes removed).  Both written atomically."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence

from kneenlp.base.atomic import write_text_atomic
from kneenlp.io.osim.kinematics import OsimError
from kneenlp.io.osim.model import _LIGAMENT_TAG, JAM_ONLY_CLASSES
from kneenlp.io.osim.read import read_osim

# --------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------
_WRITABLE = ("linear_stiffness", "slack_length", "transition_strain", "damping_coefficient")


def _fmt(v: float) -> str:
    return repr(float(v))


def write_calibrated(src_osim: str | os.PathLike, out_path: str | os.PathLike,
                     values: Mapping[str, Mapping[str, float]]) -> list[tuple[str, str, str, str]]:
    """Copy ``src_osim`` to ``out_path`` changing only the given ligament properties.

    ``values`` maps bundle name -> {property: value} with property in linear_stiffness
    [N/strain], slack_length [m], transition_strain [-], damping_coefficient.  The file is
    edited as text inside each named ``Blankevoort1991Ligament`` element: only the number
    between ``<prop>`` and ``</prop>`` changes (written with repr(), which round-trips
    exactly); if the property element is absent (OpenSim default in use) a new element is
    inserted before the ligament's closing tag with the indentation of its last child.
    All other bytes (comments, whitespace, line endings, encoding) are preserved.

    Returns a list of (bundle, property, old_text, new_text).  Raises OsimError for unknown
    bundles/properties, non-finite or non-positive values, or ``out_path == src_osim``.
    """
    src, out = os.fspath(src_osim), os.fspath(out_path)
    if os.path.abspath(src) == os.path.abspath(out):
        raise OsimError(f"{src}: write_calibrated refuses to overwrite its source")
    with open(src, "rb") as fh:
        raw = fh.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise OsimError(f"{src}: not UTF-8 ({e})") from None
    read_osim(src)  # validates the file and that all ligaments parse
    changes: list[tuple[str, str, str, str]] = []
    for bundle, props in values.items():
        pat = re.compile(r'<' + _LIGAMENT_TAG + r'\s+name\s*=\s*"' + re.escape(bundle) + r'"\s*>'
                         r'(?P<body>.*?)</' + _LIGAMENT_TAG + r'>', re.S)
        ms = list(pat.finditer(text))
        if len(ms) != 1:
            raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}' found {len(ms)} times (need 1)")
        m = ms[0]
        body, b0 = m.group("body"), m.start("body")
        # GeometryPath content is masked so that only direct property children are touched
        gp = re.search(r"<GeometryPath\b.*?</GeometryPath>", body, re.S)
        masked = body if gp is None else body[:gp.start()] + " " * (gp.end() - gp.start()) + body[gp.end():]
        edits: list[tuple[int, int, str]] = []
        for key, val in props.items():
            if key not in _WRITABLE:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}': property '{key}' not writable "
                                f"(allowed: {', '.join(_WRITABLE)})")
            v = float(val)
            if not math.isfinite(v) or (v <= 0 and key != "damping_coefficient") or v < 0:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}' <{key}>: invalid value {val!r}")
            occ = list(re.finditer(r"<" + key + r">(?P<v>[^<]*)</" + key + r">", masked))
            if len(occ) > 1:
                raise OsimError(f"{src}: {_LIGAMENT_TAG} '{bundle}': <{key}> appears {len(occ)} times")
            if occ:
                o = occ[0]
                old = o.group("v")
                lead = old[: len(old) - len(old.lstrip())]
                trail = old[len(old.rstrip()):]
                new = lead + _fmt(v) + trail
                edits.append((b0 + o.start("v"), b0 + o.end("v"), new))
                changes.append((bundle, key, old.strip(), _fmt(v)))
            else:
                # insert before closing tag, copying indentation of the last child element line
                close = m.end("body")
                line_start = text.rfind("\n", 0, close) + 1
                closing_indent = text[line_start:close]
                nl = "\r\n" if "\r\n" in body else "\n"
                child_indent = re.findall(r"\n([ \t]*)<", body)
                ind = child_indent[-1] if child_indent else closing_indent + "\t"
                ins = f"{ind}<{key}>{_fmt(v)}</{key}>{nl}"
                if closing_indent.strip() == "":
                    edits.append((line_start, line_start, ins))
                else:
                    edits.append((close, close, nl + ins))
                changes.append((bundle, key, "", _fmt(v)))
        for s, e, new in sorted(edits, reverse=True):
            text = text[:s] + new + text[e:]
    write_text_atomic(out, text)
    return changes


def write_opensim_loadable_copy(src_osim: str | os.PathLike, out_path: str | os.PathLike,
                                remove: Sequence[str] = JAM_ONLY_CLASSES) -> list[str]:
    """Write a copy of the model without the elements of the classes in ``remove``
    (default: the OpenSim JAM-only classes) so that the plain ``opensim`` package can
    load it.  Text-level removal of each ``<Class ...>...</Class>`` element (or
    self-closing ``<Class .../>``).  Returns the names of removed components.  Bodies,
    joints and ligaments are untouched, so their kinematics can be compared in OpenSim.
    Mesh files that are missing only produce OpenSim warnings."""
    with open(src_osim, "rb") as fh:
        text = fh.read().decode("utf-8")
    removed: list[str] = []
    for cls in remove:
        pat = re.compile(r"[ \t]*<" + cls + r'\b[^>]*?(/>|>.*?</' + cls + r">)[ \t]*\r?\n?", re.S)
        removed += [re.search(r'name="([^"]*)"', m.group(0)).group(1) if 'name="' in m.group(0) else cls
                    for m in pat.finditer(text)]
        text = pat.sub("", text)
    write_text_atomic(out_path, text)
    return removed


"""Reading Abaqus input files (``.inp``) of a knee's finite-element model.

Two readers, each for what it serves:

* solid and shell meshes (``*NODE``, ``*ELEMENT`` of C3D8/C3D4/R3D3..., element sets with
  ``generate``) are read with meshio (:func:`read_mesh`);
* the keywords meshio does not read (connector elements ``CONN3D2``, ``*PARAMETER`` blocks,
  ``*CONNECTOR ELASTICITY`` tables, ``*SURFACE`` definitions) by :func:`read_keywords`, a small
  keyword reader: a line starting ``**`` is a comment, a line starting ``*`` opens a keyword with
  ``KEY=VALUE`` options, the lines up to the next keyword are its data.

``*PARAMETER`` blocks are Python expressions in Abaqus; :func:`evaluate_parameters` evaluates them
with a restricted evaluator (numbers, names defined before, ``+ - * / **`` and parentheses), and
``<NAME>`` in data lines is substituted (:func:`substitute`).

Faces of solid elements (``S1`` ... ``S6``) follow Abaqus's node numbering (:data:`FACES`); the
surface of a set of solid elements (a ``*SURFACE, TYPE=ELEMENT`` naming only an element set) is its
exterior: the faces that belong to exactly one element of the set (:func:`exterior_faces`).
"""

from __future__ import annotations

import ast
import contextlib
import io
import operator
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.base.errors import InputError

#: Node indices (0-based) of each face label of Abaqus's solid elements.
FACES: dict[str, dict[str, tuple[int, ...]]] = {
    "hexahedron": {"S1": (0, 1, 2, 3), "S2": (4, 7, 6, 5), "S3": (0, 4, 5, 1), "S4": (1, 5, 6, 2),
                   "S5": (2, 6, 7, 3), "S6": (3, 7, 4, 0)},
    "tetra": {"S1": (0, 1, 2), "S2": (0, 3, 1), "S3": (1, 3, 2), "S4": (2, 3, 0)},
}


#: The keywords import-abaqus reads: what it uses (nodes, elements, surfaces, parameters, the
#: connectors' sections, behaviours and elasticity tables) and what it knowingly leaves aside because
#: it changes neither the geometry nor a ligament's static law (sets, orientations, damping, mass,
#: inertia, multi-point constraints of the frames' rigid bodies).  Any other keyword is refused by
#: name: a model part hidden behind it (an *INCLUDE of a ligament's fibres) would otherwise be dropped.
KNOWN_KEYWORDS = frozenset({
    "NODE", "ELEMENT", "ELSET", "NSET", "SURFACE", "PARAMETER", "CONNECTOR SECTION", "CONNECTOR BEHAVIOR",
    "CONNECTOR ELASTICITY", "CONNECTOR DAMPING", "MASS", "ROTARY INERTIA", "MPC", "ORIENTATION",
})


@dataclass
class Keyword:
    """One keyword of an input file: its name (upper case), options and data lines (split at commas)."""

    name: str
    options: dict[str, str]
    data: list[list[str]] = field(default_factory=list)


def read_keywords(path: str | Path) -> list[Keyword]:
    """The keywords of an ``.inp`` file in order (see module docstring); comments dropped."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", source=str(path)) from None
    out: list[Keyword] = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("**"):
            continue
        if line.startswith("*"):
            parts = [p.strip() for p in line[1:].split(",")]
            options = {}
            for p in parts[1:]:
                if p:
                    key, _, value = p.partition("=")
                    options[key.strip().upper()] = value.strip()
            name = parts[0].upper()
            if name == "INCLUDE":
                raise InputError(f"*INCLUDE of {options.get('INPUT', '?')!r} is not followed: put the included "
                                 "file's content in this file", source=str(path), field="*INCLUDE")
            if name not in KNOWN_KEYWORDS:
                raise InputError(f"keyword *{name} is not understood (import-abaqus reads "
                                 f"{', '.join('*' + k for k in sorted(KNOWN_KEYWORDS))})", source=str(path),
                                 field=f"*{name}")
            out.append(Keyword(name, options))
        elif out:
            out[-1].data.append([v.strip() for v in line.split(",") if v.strip()])
    return out


_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
        ast.Pow: operator.pow}


def _evaluate(node: ast.AST, names: dict[str, float]) -> float:
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
        return float(node.value)
    if isinstance(node, ast.Name):
        if node.id not in names:
            raise KeyError(node.id)
        return names[node.id]
    if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
        return _OPS[type(node.op)](_evaluate(node.left, names), _evaluate(node.right, names))
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        value = _evaluate(node.operand, names)
        return -value if isinstance(node.op, ast.USub) else value
    raise ValueError(f"unsupported expression {ast.dump(node)[:60]}")


def evaluate_parameters(keywords: list[Keyword], names: dict[str, float] | None = None,
                        source: str = "<inp>", scale: Mapping[str, float] | None = None) -> dict[str, float]:
    """Values of every ``*PARAMETER`` assignment in ``keywords``, evaluated in order on top of
    ``names`` (parameters of files read before); a later assignment replaces an earlier one.
    ``scale`` multiplies the named parameters where they are assigned (what depends on a parameter:
    :func:`kneenlp.io.abaqus_fibres.dependencies`)."""
    values = dict(names or {})
    scale = scale or {}
    for kw in keywords:
        if kw.name != "PARAMETER":
            continue
        for row in kw.data:
            line = ",".join(row)
            target, eq, expr = line.partition("=")
            if not eq:
                continue
            try:
                values[target.strip()] = (_evaluate(ast.parse(expr.strip(), mode="eval").body, values)
                                          * scale.get(target.strip(), 1.0))
            except KeyError as exc:
                raise InputError(f"parameter {target.strip()} uses {exc.args[0]!r}, defined nowhere before",
                                 source=source, field=target.strip()) from None
            except (SyntaxError, ValueError, ZeroDivisionError) as exc:
                raise InputError(f"cannot evaluate {line!r} ({exc})", source=source, field=target.strip()) from None
    return values


def substitute(value: str, parameters: dict[str, float], source: str = "<inp>") -> float:
    """A data value: a number, or ``<NAME>`` of a parameter."""
    value = value.strip()
    if value.startswith("<") and value.endswith(">"):
        name = value[1:-1].strip()
        if name not in parameters:
            raise InputError(f"unknown parameter <{name}>", source=source, field=name)
        return parameters[name]
    try:
        return float(value)
    except ValueError:
        raise InputError(f"expected a number or <PARAMETER>, got {value!r}", source=source) from None


def nodes(keywords: list[Keyword], source: str = "<inp>") -> dict[int, np.ndarray]:
    """Every ``*NODE`` of ``keywords``: id -> coordinates (the file's unit).  Coordinates are three
    finite numbers; a node defined twice at different places is refused (which is meant is not
    known; at the same place it is one node)."""
    out: dict[int, np.ndarray] = {}
    for kw in keywords:
        if kw.name == "NODE":
            for row in kw.data:
                try:
                    node, x = int(row[0]), np.array([float(v) for v in row[1:4]])
                except (ValueError, IndexError):
                    raise InputError(f"malformed node line {', '.join(row)!r}", source=source,
                                     field="*NODE") from None
                if x.size != 3 or not np.all(np.isfinite(x)):
                    raise InputError(f"node {node}: expected three finite coordinates, got {', '.join(row[1:])!r}",
                                     source=source, field="*NODE")
                if node in out and not np.array_equal(out[node], x):
                    raise InputError(f"node {node} is defined twice, at different places", source=source,
                                     field="*NODE")
                out[node] = x
    return out


def elements(keywords: list[Keyword], element_type: str | None = None) -> dict[str, list[tuple[int, ...]]]:
    """Elements of ``*ELEMENT`` keywords (of ``element_type`` if given) by their ``ELSET``: lists of
    node-id tuples (the element id dropped)."""
    out: dict[str, list[tuple[int, ...]]] = {}
    for kw in keywords:
        if kw.name == "ELEMENT" and (element_type is None or kw.options.get("TYPE", "").upper() == element_type):
            out.setdefault(kw.options.get("ELSET", ""), []).extend(tuple(int(v) for v in row[1:]) for row in kw.data)
    return out


@dataclass
class SolidMesh:
    """A solid mesh read with meshio: points (file unit), cells by type, element sets (indices
    into ``cells[type]``, per type)."""

    points: np.ndarray
    cells: dict[str, np.ndarray]
    sets: dict[str, dict[str, np.ndarray]]
    source: str

    def faces(self, element_set: str, label: str | None = None) -> np.ndarray:
        """Outward-oriented faces (node indices) of ``element_set``: the ``label`` face (``"S1"``)
        of each element, or without ``label`` the set's exterior (:func:`exterior_faces`)."""
        if element_set not in self.sets:
            raise InputError(f"no element set {element_set!r}; known: {', '.join(sorted(self.sets))}",
                             source=self.source, field=element_set)
        out = []
        for ctype, idx in self.sets[element_set].items():
            if ctype not in FACES:
                raise InputError(f"element set {element_set!r} holds {ctype} elements, which have no solid faces",
                                 source=self.source, field=element_set)
            conn = self.cells[ctype][idx]
            if label is None:
                out.append(exterior_faces(self.points, conn, ctype))
            else:
                out.append(orient_outward(self.points, conn, conn[:, FACES[ctype][label.upper()]]))
        return np.vstack(out)


def read_mesh(path: str | Path) -> SolidMesh:
    """A solid or shell mesh with its element sets, read by meshio (errors as one line)."""
    import meshio

    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", source=str(path))
    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            mesh = meshio.read(path, file_format="abaqus")
    except (Exception, SystemExit) as exc:  # meshio raises many kinds and may call sys.exit
        said = " ".join((sink.getvalue() or str(exc) or type(exc).__name__).split())
        raise InputError(f"meshio cannot read it ({said[:160]})", source=str(path)) from None
    cells: dict[str, list[np.ndarray]] = {}
    offsets: list[tuple[str, int]] = []
    for block in mesh.cells:
        start = sum(len(c) for c in cells.get(block.type, []))
        cells.setdefault(block.type, []).append(np.asarray(block.data))
        offsets.append((block.type, start))
    sets: dict[str, dict[str, np.ndarray]] = {}
    for name, per_block in mesh.cell_sets.items():
        for (ctype, start), idx in zip(offsets, per_block, strict=True):
            if idx is not None and len(idx):
                sets.setdefault(name, {})
                prev = sets[name].get(ctype, np.zeros(0, int))
                sets[name][ctype] = np.concatenate([prev, np.asarray(idx, int) + start])
    return SolidMesh(np.asarray(mesh.points, float), {k: np.vstack(v) for k, v in cells.items()}, sets, str(path))


def orient_outward(points: np.ndarray, conn: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` (one per element of ``conn``) reordered where needed so that their normal (right
    hand over the node order) points away from their element's centroid."""
    faces = np.array(faces)
    centre = points[conn].mean(axis=1)
    p = points[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, -1] - p[:, 0])
    inward = np.einsum("ij,ij->i", normal, p.mean(axis=1) - centre) < 0
    faces[inward] = faces[inward, ::-1]
    return faces


def exterior_faces(points: np.ndarray, conn: np.ndarray, ctype: str) -> np.ndarray:
    """Faces of solid elements ``conn`` that belong to one element only, oriented outwards."""
    labels = FACES[ctype]
    all_faces = np.vstack([conn[:, idx] for idx in labels.values()])
    owner = np.tile(np.arange(len(conn)), len(labels))
    key = np.sort(all_faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    return orient_outward(points, conn[owner[once]], all_faces[once])


def triangles(faces: np.ndarray) -> np.ndarray:
    """Quadrilateral faces split into two triangles each (triangles unchanged)."""
    faces = np.asarray(faces)
    if faces.shape[1] == 3:
        return faces
    return np.vstack([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])

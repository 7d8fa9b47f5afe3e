"""File schemas: the tables of the package's TOML files declared as pydantic models, and their
validation errors as the package's one-line :class:`~kneenlp.base.errors.InputError`.

Every table is a :class:`Table` (unknown keys are refused); values use the types here, whose
messages are the package's own (``expected a number, got 'x'``).  :func:`validated` checks a
document against a model and raises the first problem as an :class:`InputError` naming the file
and the field, written as the files' fields are named everywhere (``cases[0].exclude[1].flexion``).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Callable, Iterable
from typing import Annotated, Any, TypeVar

from pydantic import BaseModel, BeforeValidator, ConfigDict, TypeAdapter, ValidationError, ValidationInfo
from pydantic_core import PydanticCustomError

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.tomlfile import not_a_number

M = TypeVar("M", bound=BaseModel)


class Table(BaseModel):
    """A TOML table of a file: its keys are the fields; any other key is an error."""

    model_config = ConfigDict(extra="forbid")


def fail(message: str, key: str | None = None) -> PydanticCustomError:
    """A validation error with the package's ``message``; ``key``: the field below the validated
    one it concerns (a model validator naming one of its fields)."""
    return PydanticCustomError("kneenlp", "{message}", {"message": message, "key": key})


def to_number(value: object) -> float:
    """A finite float from a TOML value (an integer too, a boolean not)."""
    problem = not_a_number(value)
    if problem:
        raise fail(problem)
    return float(value)


def to_numbers(value: object) -> list[float]:
    """A number or a non-empty array of numbers, as a list of finite floats."""
    items = value if isinstance(value, list) else [value]
    if not items:
        raise fail("expected a number or a non-empty array of numbers, got []")
    return [to_number(v) for v in items]


def to_point(value: object, info: ValidationInfo) -> tuple[float, float, float]:
    """``[x, y, z]`` in the file's length unit (the validation context's ``units``)."""
    if not isinstance(value, list) or len(value) != 3:
        units = (info.context or {}).get("units", "the file's unit")
        raise fail(f"expected [x, y, z] in {units}, got {value!r}")
    x, y, z = (to_number(v) for v in value)
    return x, y, z


def to_name(value: object) -> str:
    """A non-empty string (a file name, a label)."""
    if not isinstance(value, str) or not value.strip():
        raise fail(f"expected a non-empty string, got {value!r}")
    return value


def to_flag(value: object) -> bool:
    """A TOML boolean (``true`` or ``false``; not a string or a number pydantic would read as one)."""
    if not isinstance(value, bool):
        raise fail(f"expected true or false, got {value!r}")
    return value


def one_of(kind: str, known: Iterable[str]) -> BeforeValidator:
    """A string among ``known``: else ``unknown <kind> 'x'; known: a, b``."""
    names = tuple(known)

    def check(value: object) -> object:
        if not isinstance(value, str) or value not in names:
            raise fail(unknown_name(kind, str(value), names).message)
        return value
    return BeforeValidator(check)


#: A finite number (int or float in the file, never a boolean), as a float.
Number = Annotated[float, BeforeValidator(to_number)]
#: A number or a non-empty array of numbers, as a list of floats (an error names the whole field).
Numbers = Annotated[list[float], BeforeValidator(to_numbers)]
#: A point ``[x, y, z]`` (an error names the whole point).
Point = Annotated[tuple[float, float, float], BeforeValidator(to_point)]
#: ``true`` or ``false``.
Flag = Annotated[bool, BeforeValidator(to_flag)]
#: A non-empty string.
Name = Annotated[str, BeforeValidator(to_name)]


def validated(schema: type[M] | Any, doc: object, source: str | None, *, prefix: tuple = (),
              context: dict | None = None) -> M | Any:
    """``doc`` checked against ``schema`` (a :class:`Table` or a type of them, e.g. ``dict[str,
    Entry]``), or the first problem as a one-line :class:`InputError` naming ``source`` and the
    field (``prefix``: the fields above ``doc`` in its file)."""
    try:
        if isinstance(schema, type) and issubclass(schema, BaseModel):
            return schema.model_validate(doc, context=context)
        return TypeAdapter(schema).validate_python(doc, context=context)
    except ValidationError as exc:
        raise input_error(exc, schema, source, prefix) from None


def input_error(exc: ValidationError, model: Any, source: str | None, prefix: tuple = ()) -> InputError:
    """The first error of ``exc`` (validating the schema ``model``) as an :class:`InputError`; an
    unknown key first of all (``stiffness = 1e4`` for ``k`` is a misnamed ``k``, not a missing one)."""
    errors = exc.errors(include_url=False)
    err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    loc = tuple(p for p in err["loc"] if p != "[key]")
    ctx = err.get("ctx") or {}
    if ctx.get("key"):
        loc = (*loc, ctx["key"])
    value = err.get("input")
    kind = err["type"]
    if kind == "kneenlp":
        message = ctx["message"]
    elif kind == "extra_forbidden":
        parent = _model_at(model, loc[:-1])
        known = ", ".join(_keys(parent)) if parent else ""
        message = f"unknown key {loc[-1]!r}" + (f"; known: {known}" if known else "")
    elif kind == "missing":
        parent = _model_at(model, loc[:-1])
        info = parent.model_fields.get(str(loc[-1])) if parent else None
        message = "missing" + (f" {info.description}" if info is not None and info.description else "")
    elif kind == "literal_error":
        message = f"must be {ctx['expected']}, got {value!r}"
    elif kind in ("model_type", "model_attributes_type", "dict_type"):
        found = _model_at(model, loc)
        message = (f"must be a table ({', '.join(_keys(found))})" if found else "must be a table") + f", got {value!r}"
    elif kind in ("list_type", "tuple_type"):
        message = f"expected an array, got {value!r}"
    elif kind == "string_type":
        message = f"expected a string, got {value!r}"
    elif kind == "bool_type":
        message = f"expected true or false, got {value!r}"
    elif kind == "too_short":
        message = "must not be empty"
    else:
        message = f"{err['msg']}, got {value!r}"
    return InputError(message, source=source, field=dotted((*prefix, *loc)) or None)


def dotted(loc: Iterable[str | int]) -> str:
    """A field path as the files' fields are named: ``cases[0].exclude[1].flexion``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _keys(model: type[BaseModel]) -> list[str]:
    """The keys of a table, in their declared order."""
    return list(model.model_fields)


def _model_at(model: Any, loc: tuple) -> type[BaseModel] | None:
    """The table model at ``loc`` below ``model`` (through arrays, tables of tables and optional
    values), or None where ``loc`` leads elsewhere."""
    current: Any = model
    for part in loc:
        current = _table_of(current)
        if isinstance(part, int):
            current = _element(current, list)
        elif isinstance(current, type) and issubclass(current, BaseModel):
            field = current.model_fields.get(part)
            current = field.annotation if field is not None else None
        else:
            current = _element(current, dict)
    current = _table_of(current)
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def _table_of(annotation: Any) -> Any:
    """``annotation`` without ``Annotated`` and ``None``: a model of an optional table."""
    while typing.get_origin(annotation) is Annotated:
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _table_of(options[0]) if len(options) == 1 else annotation
    return annotation


def _element(annotation: Any, container: Callable) -> Any:
    """The element type of a ``list[X]`` or the value type of a ``dict[K, X]``."""
    if typing.get_origin(annotation) is container:
        return typing.get_args(annotation)[-1]
    return None

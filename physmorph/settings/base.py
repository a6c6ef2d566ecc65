"""How every config class is declared: a frozen pydantic dataclass whose fields carry their default,
their bounds and one line of meaning (and unit), so the validation, the JSON schema and
config/README.md all come from the one declaration.

A field reads ``name: Annotated[Float, setting("meaning", unit="s", gt=0)] = 0.5``. ``Float``,
``Int`` and ``Bool`` accept what a YAML file or ``snakemake --config`` hands over (numbers as int,
float or numeric string, ``"true"``/``"false"``) and refuse the rest (a bool is not a number).
A check across fields raises :class:`Refused` naming the field. :func:`settings_dataclass` turns
pydantic's errors into the class's own error type whose key is the dotted path of the refused
value (``mpm.smoothing``, ``shapes.bunny.file``, ``tables.shapes[0]``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import re
import types
from typing import Annotated, Any, Union, get_args, get_origin, get_type_hints

import annotated_types
import pydantic
from pydantic import BeforeValidator, ConfigDict, Field, ValidationError

from physmorph.settings.errors import ConfigError


class Refused(ValueError):
    """A value a check across fields refuses: ``field`` the field it names, the message why."""

    def __init__(self, field: str, reason: str):
        super().__init__(reason)
        self.field = field


def _as_number(given: Any, what: str = "a number") -> float:
    value = given
    if isinstance(given, str):
        try:
            value = float(given.strip())
        except ValueError:
            raise ValueError(f"expected {what}, got {given!r}") from None
    elif isinstance(given, bool) or not isinstance(given, numbers.Real):
        raise ValueError(f"expected {what}, got {given!r}")
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {given!r}")
    return value


def _as_float(value: Any) -> float:
    return float(_as_number(value))


def _as_integer(value: Any) -> int:
    number = _as_number(value, "an integer")
    if isinstance(number, numbers.Integral):
        return int(number)
    if not float(number).is_integer():
        raise ValueError(f"expected an integer, got {value!r}")
    return int(number)


def _as_bool(value: Any) -> bool:
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    if type(value).__name__ in ("bool", "bool_"):  # Python's and numpy's
        return bool(value)
    raise ValueError(f"expected true or false, got {value!r}")


# what a field's type is written as: a number from YAML, from --config (a string) or from code
Float = Annotated[float, BeforeValidator(_as_float)]
Int = Annotated[int, BeforeValidator(_as_integer)]
Bool = Annotated[bool, BeforeValidator(_as_bool)]


def setting(meaning: str, unit: str = "", range_note: str = "", job: str = "", **bounds) -> Any:
    """A field's declaration: its meaning (the description), unit, bounds (ge, gt, le, lt) and,
    for a range no bound can say (a check across fields), ``range_note`` in words; ``job``: the
    one workflow job that reads it, where a section serves several (fields_of_job)."""
    extra = {k: v for k, v in (("unit", unit), ("range", range_note), ("job", job)) if v}
    return Field(description=meaning, json_schema_extra=extra or None, **bounds)


def fields_of_job(cls: type, job: str) -> tuple[str, ...]:
    """The fields of the config class ``cls`` declared with ``setting(..., job=job)``, in order."""
    return tuple(name for name, info in cls.__pydantic_fields__.items()
                 if isinstance(info.json_schema_extra, dict) and info.json_schema_extra.get("job") == job)


def settings_dataclass(cls=None, *, error: type[ValueError] = ConfigError):
    """``cls`` as a frozen pydantic dataclass that refuses unknown keys and raises ``error`` (a
    ValueError with ``key`` and ``reason``) naming the refused value's dotted key."""

    def wrap(cls):
        out = pydantic.dataclasses.dataclass(cls, frozen=True,
                                             config=ConfigDict(extra="forbid", allow_inf_nan=False))
        validated_init = out.__init__

        def __init__(self, *args, **kwargs):
            try:
                validated_init(self, *args, **kwargs)
            except ValidationError as exc:
                key, reason = refusal(type(self), exc)
                raise make_error(error, key, reason) from None

        __init__.__doc__ = validated_init.__doc__
        out.__init__ = __init__
        return out

    return wrap if cls is None else wrap(cls)


def make_error(error: type[ValueError], key: str, reason: str) -> ValueError:
    """``error`` refusing ``key``: a ConfigError says ``config key 'key': reason``; another error
    type says the reason (named by its key where the reason does not start with it)."""
    if issubclass(error, ConfigError):
        return error.for_key(key or "<root>", reason)
    exc = error(reason if not key or reason.startswith(key.split(".")[-1]) else f"{key}: {reason}")
    exc.key, exc.reason = key, reason
    return exc


# --------------------------------------------------------------------------------------------
# What a field allows, in words (error messages and config/README.md)
# --------------------------------------------------------------------------------------------

def bounds(info) -> dict[str, Any]:
    """The field's numeric bounds: {"ge": 0, "lt": 1} and the like."""
    out = {}
    for m in info.metadata:
        for kind in ("ge", "gt", "le", "lt"):
            if isinstance(m, getattr(annotated_types, kind.capitalize())):
                out[kind] = getattr(m, kind)
    return out


def _number_text(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def range_text(info, with_note: bool = True) -> str:
    """What a field's bounds allow: ">= 1", "> 0", "[0, 1)", "(0, 1]"; with_note: its range note
    instead, where it has one (a range across fields)."""
    note = info.json_schema_extra.get("range") if isinstance(info.json_schema_extra, dict) else None
    if note and with_note:
        return note
    b = bounds(info)
    return interval_text(b.get("ge"), b.get("gt"), b.get("le"), b.get("lt"))


def interval_text(ge=None, gt=None, le=None, lt=None) -> str:
    """Bounds in words: ">= 1", "> 0", "[0, 1)", "(0, 1]" ("" without any)."""
    lo = ("[", ge) if ge is not None else ("(", gt) if gt is not None else None
    hi = ("]", le) if le is not None else (")", lt) if lt is not None else None
    if lo and hi:
        return f"{lo[0]}{_number_text(lo[1])}, {_number_text(hi[1])}{hi[0]}"
    if lo:
        return f"{'>=' if lo[0] == '[' else '>'} {_number_text(lo[1])}"
    if hi:
        return f"{'<=' if hi[0] == ']' else '<'} {_number_text(hi[1])}"
    return ""


def field_default(f: dataclasses.Field) -> Any:
    """A dataclass field's default (its factory called), or dataclasses.MISSING."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


# --------------------------------------------------------------------------------------------
# pydantic's errors as one dotted key and a reason
# --------------------------------------------------------------------------------------------

def _unwrap(tp: Any) -> Any:
    while get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    return tp


def _step(tp: Any, part: Any) -> tuple[Any, str | None]:
    """(the type one loc part further, that part as a key piece; None: the part was a union's tag)."""
    tp = _unwrap(tp)
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:  # X | None: pydantic's nullable X, no tag of its own
            return _step(args[0], part)
        return Any, None
    if dataclasses.is_dataclass(tp) and isinstance(part, str):
        info = getattr(tp, "__pydantic_fields__", {}).get(part)
        return (info.annotation if info is not None else get_type_hints(tp).get(part, Any)), part
    if get_origin(tp) is dict:
        return get_args(tp)[1], str(part)
    if get_origin(tp) is tuple and isinstance(part, int):
        args = get_args(tp)
        return (args[0] if len(args) == 2 and args[1] is Ellipsis else args[min(part, len(args) - 1)]), f"[{part}]"
    return Any, (f"[{part}]" if isinstance(part, int) else str(part))


def _container(tp: Any) -> Any:
    """The type a key is looked up in: a dataclass or mapping, past Annotated and Optional."""
    tp = _unwrap(tp)
    if get_origin(tp) in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        return _container(args[0]) if len(args) == 1 else tp
    return tp


def _key_of(cls, loc: tuple) -> tuple[str, Any]:
    """The dotted key of a pydantic error location, and the type whose member it names last."""
    key, tp, parent = "", cls, cls
    for part in loc:
        container = _container(tp)
        tp, piece = _step(tp, part)
        if piece is not None:
            parent = container
            key = key + piece if piece.startswith("[") or not key else f"{key}.{piece}"
    return key, parent


def _reason(err: dict, name: str, parent) -> str:
    kind, value, ctx = err["type"], err.get("input"), err.get("ctx") or {}
    if kind == "value_error" and "error" in ctx:
        return str(ctx["error"])
    if kind == "literal_error":
        choices = re.findall(r"'([^']*)'", ctx["expected"])
        return f"{value!r} is not allowed (allowed: {', '.join(choices)})"
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        info = getattr(parent, "__pydantic_fields__", {}).get(name)
        rule = range_text(info, with_note=False) if info is not None else err["msg"]
        return f"{name} must be {'in ' if rule[:1] in '[(' else ''}{rule}, got {value!r}"
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        allowed = sorted(f.name for f in dataclasses.fields(parent) if f.init) if dataclasses.is_dataclass(parent) else []
        return f"unknown key (allowed: {', '.join(allowed)})"
    if kind == "string_pattern_mismatch":
        info = getattr(parent, "__pydantic_fields__", {}).get(name)
        return f"must be {range_text(info) if info is not None else ctx.get('pattern')}, got {value!r}"
    if kind == "missing":
        return "required, not set"
    if kind in ("dataclass_type", "dataclass_args_type", "dict_type"):
        return f"expected a mapping, got {value!r}"
    if kind in ("tuple_type", "list_type"):
        return f"expected a list, got {value!r}"
    if kind == "string_type":
        return f"expected a string, got {value!r}"
    if kind == "finite_number":
        return f"expected a finite number, got {value!r}"
    return f"{err['msg'][0].lower()}{err['msg'][1:]}, got {value!r}"


def refusal(cls, exc: ValidationError, skip: int = 0) -> tuple[str, str]:
    """(dotted key, reason) of the first error pydantic reports, the first ``skip`` parts of its
    location left out; a check across fields (:class:`Refused`) names its field below the object
    it checks."""
    err = exc.errors()[0]
    loc = tuple(err["loc"])[skip:]
    error = (err.get("ctx") or {}).get("error")
    if isinstance(error, Refused):
        loc += (error.field,)
    key, parent = _key_of(cls, loc)
    return key, _reason(err, re.split(r"[.\[]", key)[-1] if key else "", parent)


@functools.lru_cache(maxsize=None)
def _holder(cls) -> type[pydantic.BaseModel]:
    # a plain dataclass takes the config of what holds it: unknown keys refused, no inf or nan
    return pydantic.create_model(f"{cls.__name__}Holder", __config__=ConfigDict(extra="forbid", allow_inf_nan=False),
                                 value=(cls, ...))


def validate_plain_dataclass(cls, data: dict, error: type[ValueError] = ConfigError):
    """A plain (standard-library) dataclass ``cls`` from ``data``, validated by pydantic as a config
    class is; ``error`` names the refused value's dotted key."""
    try:
        return _holder(cls).model_validate({"value": data}).value
    except ValidationError as exc:
        key, reason = refusal(cls, exc, skip=1)
        raise make_error(error, key, reason) from None


def with_prefix(where: str, key: str) -> str:
    if not where:
        return key
    return f"{where}{key}" if key.startswith("[") else f"{where}.{key}" if key else where


# --------------------------------------------------------------------------------------------
# The JSON schema of a config class, inline (no $ref), for the workflow's validation
# --------------------------------------------------------------------------------------------

# a bound pydantic leaves under its own name (a number type behind a validator): its JSON-schema keyword
JSON_BOUNDS = {"ge": "minimum", "gt": "exclusiveMinimum", "le": "maximum", "lt": "exclusiveMaximum"}
BOOLEAN_PATTERN = r"^\s*([Tt][Rr][Uu][Ee]|[Ff][Aa][Ll][Ss][Ee])\s*$"
NUMBER_PATTERN = r"^\s*[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?\s*$"


def _inline(node: Any, defs: dict) -> Any:
    if isinstance(node, dict):
        if "$ref" in node:
            target = _inline(defs[node["$ref"].split("/")[-1]], defs)
            return {**target, **{k: _inline(v, defs) for k, v in node.items() if k != "$ref"}}
        return {k: _inline(v, defs) for k, v in node.items() if k not in ("title", "$defs")}
    if isinstance(node, list):
        return [_inline(v, defs) for v in node]
    return node


def _accept_strings(node: Any) -> Any:
    """Numbers and booleans may come as strings (``--config 'mpm={smoothing: 0.5}'``): the schema
    accepts a numeric string for a number and "true"/"false" for a boolean, as the settings do."""
    if isinstance(node, list):
        return [_accept_strings(v) for v in node]
    if not isinstance(node, dict):
        return node
    out = {JSON_BOUNDS.get(k, k): _accept_strings(v) for k, v in node.items()}
    if "properties" in out and "description" in out:  # a class's docstring: its first line says what it is
        out["description"] = out["description"].strip().splitlines()[0]
    if out.get("type") in ("number", "integer"):
        out["type"] = [out["type"], "string"]
        out["pattern"] = NUMBER_PATTERN
    elif out.get("type") == "boolean":
        out["type"] = ["boolean", "string"]
        out["pattern"] = BOOLEAN_PATTERN
    if "enum" in out and "type" in out and "const" not in out:
        del out["type"]  # the choices say it
    return out


def json_schema_of(cls) -> dict:
    """The class's JSON schema (draft 2020-12) as pydantic makes it, with its definitions inline."""
    raw = pydantic.TypeAdapter(cls).json_schema()
    return _accept_strings(_inline(raw, raw.get("$defs", {})))


"""A fast checker for the subset of JSON Schema that starlog's channel schemas use.

The schema is compiled to one straight-line Python predicate that answers valid / invalid; only
for an invalid value is the schema walked again, to name the first violation with its JSON path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from starlog.errors import InvalidInputError

__all__ = ["compile_json_schema"]

_JSON_TYPES: dict[str, Any] = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "integer": lambda v: (isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, float) and v.is_integer()),
}

_SUPPORTED = {"$schema", "$id", "title", "description", "type", "properties", "required", "additionalProperties",
              "items", "minItems", "maxItems", "minimum", "maximum", "enum", "unit", "examples", "default"}


def compile_json_schema(schema: dict[str, Any]) -> Callable[..., str | None]:
    """A fast checker for the subset of JSON Schema starlog's schemas use.

    Returns a function ``check(value) -> str | None`` giving the first violation (with its JSON
    path) or ``None``. Supported keywords: type, properties, required, additionalProperties, items,
    minItems, maxItems, minimum, maximum, enum. The schema is compiled to Python source (one
    straight-line function, no per-keyword calls), which answers valid/invalid; only for an
    invalid value is the schema walked again to name the violation. Raises
    :class:`InvalidInputError` for a schema that uses anything else.
    """
    explain = _compile_walker(schema)
    try:
        is_valid = _compile_predicate(schema)
    except (SyntaxError, RecursionError, MemoryError):  # nested deeper than Python's block limit: walk it
        def is_valid(value: Any) -> bool:
            return explain(value, "$") is None

    def check(value: Any, path: str = "$") -> str | None:
        if is_valid(value):
            return None
        return explain(value, path) or f"{path}: does not match the schema"

    return check


def _type_test(kind: str, var: str) -> str:
    """A Python expression true when ``var`` (a decoded JSON value) has JSON type ``kind``."""
    return {
        "object": f"type({var}) is dict",
        "array": f"type({var}) is list",
        "string": f"type({var}) is str",
        "boolean": f"type({var}) is bool",
        "null": f"{var} is None",
        "number": f"(type({var}) is float or type({var}) is int)",
        "integer": f"(type({var}) is int or (type({var}) is float and {var}.is_integer()))",
    }[kind]


class _PredicateSource:
    """Python source of a function returning False at the first violation of a schema."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.functions: list[str] = []  # column checkers and their tables, defined beside ``is_valid``
        self.constants: dict[str, Any] = {}
        self._names = 0

    def name(self, prefix: str) -> str:
        self._names += 1
        return f"{prefix}{self._names}"

    def constant(self, value: Any) -> str:
        key = self.name("C")
        self.constants[key] = value
        return key

    def emit(self, schema: dict[str, Any], var: str, indent: int) -> None:
        pad = "    " * indent
        out = self.lines.append
        _check_keywords(schema)
        kind = schema.get("type")
        kinds = [kind] if isinstance(kind, str) else list(kind or [])
        if kinds:
            out(f"{pad}if not ({' or '.join(_type_test(k, var) for k in kinds)}): return False")
        if "enum" in schema:
            out(f"{pad}if {var} not in {self.constant(list(schema['enum']))}: return False")
        guard = "" if kinds and set(kinds) <= {"number", "integer"} else f"{_type_test('number', var)} and "
        for key, op in (("minimum", "<"), ("maximum", ">")):
            if key in schema:
                out(f"{pad}if {guard}{var} {op} {self.constant(schema[key])}: return False")
        self._emit_object(schema, var, indent)
        self._emit_array(schema, var, indent)

    def _emit_object(self, schema: dict[str, Any], var: str, indent: int) -> None:
        props = schema.get("properties", {})
        required = list(schema.get("required", []))
        extra = schema.get("additionalProperties", True)
        if not (props or required or extra is not True):
            return
        pad = "    " * indent
        out = self.lines.append
        out(f"{pad}if type({var}) is dict:")
        if required:
            out(f"{pad}    if not {self.constant(frozenset(required))} <= {var}.keys(): return False")
        if extra is False:
            out(f"{pad}    if not {var}.keys() <= {self.constant(frozenset(props))}: return False")
        elif isinstance(extra, dict):
            item = self.name("v")
            out(f"{pad}    for _k, {item} in {var}.items():")
            out(f"{pad}        if _k not in {self.constant(frozenset(props))}:")
            self.emit(extra, item, indent + 3)
        for key, sub in props.items():
            item = self.name("v")
            if key in required:
                out(f"{pad}    {item} = {var}[{key!r}]")
                self.emit(sub, item, indent + 1)
            else:
                out(f"{pad}    if {key!r} in {var}:")
                out(f"{pad}        {item} = {var}[{key!r}]")
                self.emit(sub, item, indent + 2)
        out(f"{pad}    pass")

    def _emit_array(self, schema: dict[str, Any], var: str, indent: int) -> None:
        items = schema.get("items")
        low, high = schema.get("minItems"), schema.get("maxItems")
        if not (isinstance(items, dict) or low is not None or high is not None):
            return
        pad = "    " * indent
        out = self.lines.append
        out(f"{pad}if type({var}) is list:")
        if low is not None:
            out(f"{pad}    if len({var}) < {int(low)}: return False")
        if high is not None:
            out(f"{pad}    if len({var}) > {int(high)}: return False")
        if not isinstance(items, dict):
            return
        item = self.name("v")
        if _is_record(items):  # rows of one record type: check column by column, in C loops
            props = items["properties"]
            keys, table = self.name("k"), self.name("COLUMNS")
            columns = ", ".join(f"{key!r}: {self._column_function(sub)}" for key, sub in props.items())
            self.functions.append(f"{table} = {{{columns}}}")
            out(f"{pad}    {keys} = tuple({var}[0]) if {var} and type({var}[0]) is dict else ()")
            out(f"{pad}    if len({keys}) == {len(props)} and {self.constant(frozenset(props))}.issuperset({keys}) "
                f"and all(type(_i) is dict and tuple(_i) == {keys} for _i in {var}):")
            out(f"{pad}        for _name, _column in zip({keys}, zip(*[_i.values() for _i in {var}])):")
            out(f"{pad}            if not {table}[_name](_column): return False")
            out(f"{pad}    else:")
            out(f"{pad}        for {item} in {var}:")
            self.emit(items, item, indent + 3)
            out(f"{pad}            pass")
            return
        out(f"{pad}    for {item} in {var}:")
        self.emit(items, item, indent + 2)
        out(f"{pad}        pass")

    def _column_function(self, schema: dict[str, Any]) -> str:
        """Name of a generated ``column(values) -> bool``: every value of one property satisfies ``schema``."""
        name = self.name("column")
        saved, self.lines = self.lines, []
        out = self.lines.append
        _check_keywords(schema)
        kind = schema.get("type")
        kinds = [kind] if isinstance(kind, str) else list(kind or [])
        numeric = bool(kinds) and set(kinds) <= {"number", "integer"}
        if not set(schema) <= _ANNOTATIONS | {"type", "enum", "minimum", "maximum"}:
            self.lines.append("    for x in c:")
            self.emit(schema, "x", 2)
            out("        pass")
        else:
            if kinds:
                allowed = frozenset(t for k in kinds for t in _PYTHON_TYPES[k])
                out("    ts = set(map(type, c))")
                out(f"    if not ts <= {self.constant(allowed)}: return False")
                if "integer" in kinds and "number" not in kinds:
                    out("    if float in ts and not all(x.is_integer() for x in c if type(x) is float): return False")
            if "enum" in schema:
                out("    for x in c:")
                out(f"        if x not in {self.constant(list(schema['enum']))}: return False")
            for key, low_or_high in (("minimum", "min(c) <"), ("maximum", "max(c) >")):
                if key in schema and numeric:
                    out(f"    if {low_or_high} {self.constant(schema[key])}: return False")
                elif key in schema:
                    out("    for x in c:")
                    out(f"        if (type(x) is float or type(x) is int) and x {'<' if key == 'minimum' else '>'} "
                        f"{self.constant(schema[key])}: return False")
        self.functions.append(f"def {name}(c):\n" + "\n".join(self.lines) + "\n    return True")
        self.lines = saved
        return name


#: Keywords that say nothing about validity.
_ANNOTATIONS = {"$schema", "$id", "title", "description", "unit", "examples", "default"}

#: Python types of decoded JSON values, per JSON Schema type.
_PYTHON_TYPES: dict[str, tuple[type, ...]] = {
    "object": (dict,), "array": (list,), "string": (str,), "boolean": (bool,), "null": (type(None),),
    "number": (int, float), "integer": (int, float),
}


def _is_record(schema: dict[str, Any]) -> bool:
    """Whether ``schema`` describes objects with exactly its listed properties, all required."""
    props = schema.get("properties")
    return (isinstance(props, dict) and bool(props) and schema.get("type", "object") == "object"
            and schema.get("additionalProperties") is False and set(schema.get("required", [])) == set(props)
            and set(schema) <= _ANNOTATIONS | {"type", "properties", "required", "additionalProperties"})


def _compile_predicate(schema: dict[str, Any]) -> Callable[[Any], bool]:
    """``is_valid(value) -> bool`` for ``schema``, generated as Python source and compiled once."""
    source = _PredicateSource()
    source.emit(schema, "value", 1)
    text = "def is_valid(value):\n" + "\n".join(source.lines) + "\n    return True\n\n" + "\n".join(source.functions)
    namespace: dict[str, Any] = dict(source.constants)
    exec(compile(text, "<starlog json schema>", "exec"), namespace)  # source built above from the schema only
    return namespace["is_valid"]  # type: ignore[no-any-return]


def _check_keywords(schema: Any) -> None:
    if not isinstance(schema, dict):
        raise InvalidInputError(f"a JSON Schema must be an object, got {type(schema).__name__}.")
    unknown = set(schema) - _SUPPORTED
    if unknown:
        raise InvalidInputError(f"JSON Schema keyword(s) {sorted(unknown)} are not supported by the fast checker.")
    kind = schema.get("type")
    kinds = [kind] if isinstance(kind, str) else list(kind or [])
    if any(k not in _JSON_TYPES for k in kinds):
        raise InvalidInputError(f"unknown JSON type in {kinds}.")
    for key in ("minimum", "maximum"):
        if key in schema and (isinstance(schema[key], bool) or not isinstance(schema[key], (int, float))):
            raise InvalidInputError(f"JSON Schema {key} must be a number, got {schema[key]!r}.")
    for key in ("minItems", "maxItems"):
        if key in schema and (isinstance(schema[key], bool) or not isinstance(schema[key], int)):
            raise InvalidInputError(f"JSON Schema {key} must be an integer, got {schema[key]!r}.")
    if not isinstance(schema.get("properties", {}), dict) or not isinstance(schema.get("required", []), list):
        raise InvalidInputError("JSON Schema properties must be an object and required a list.")
    if not all(isinstance(k, str) for k in schema.get("required", [])):
        raise InvalidInputError("JSON Schema required must list property names.")
    if "enum" in schema and not isinstance(schema["enum"], list):
        raise InvalidInputError("JSON Schema enum must be a list.")


def _compile_walker(schema: dict[str, Any]) -> Any:
    """The schema as nested closures: slower, but names the first violation and its JSON path."""
    _check_keywords(schema)
    checks = _value_checks(schema)
    for composite in (_object_check(schema), _array_check(schema)):
        if composite is not None:
            checks.append(composite)

    def check(value: Any, path: str = "$") -> str | None:
        for c in checks:
            problem = c(value, path)
            if problem:
                return problem
        return None

    return check


def _value_checks(schema: dict[str, Any]) -> list[Any]:
    """The checks of the value itself: its type, enum, minimum and maximum."""
    checks: list[Any] = []
    kind = schema.get("type")
    if kind is not None:
        kinds = [kind] if isinstance(kind, str) else list(kind)
        tests = [_JSON_TYPES[k] for k in kinds]
        checks.append(lambda v, p: None if any(t(v) for t in tests) else f"{p}: expected {'/'.join(kinds)}, "
                      f"got {type(v).__name__}")
    if "enum" in schema:
        allowed = list(schema["enum"])
        checks.append(lambda v, p: None if v in allowed else f"{p}: {v!r} is not one of {allowed}")
    if "minimum" in schema:
        lo = schema["minimum"]
        checks.append(lambda v, p: f"{p}: {v!r} < minimum {lo}" if _JSON_TYPES["number"](v) and v < lo else None)
    if "maximum" in schema:
        hi = schema["maximum"]
        checks.append(lambda v, p: f"{p}: {v!r} > maximum {hi}" if _JSON_TYPES["number"](v) and v > hi else None)
    return checks


def _object_check(schema: dict[str, Any]) -> Any:
    """The check of an object's properties (required, each one's schema, additional ones), or None."""
    props = {k: _compile_walker(v) for k, v in schema.get("properties", {}).items()}
    required = list(schema.get("required", []))
    extra = schema.get("additionalProperties", True)
    extra_check = _compile_walker(extra) if isinstance(extra, dict) else None
    if not (props or required or extra is not True):
        return None

    def check_object(v: Any, p: str) -> str | None:
        if not isinstance(v, dict):
            return None
        for key in required:
            if key not in v:
                return f"{p}: missing required property {key!r}"
        for key, item in v.items():
            sub = props.get(key)
            if sub is not None:
                problem = sub(item, f"{p}.{key}")
            elif extra is False:
                problem = f"{p}: unexpected property {key!r}"
            elif extra_check is not None:
                problem = extra_check(item, f"{p}.{key}")
            else:
                problem = None
            if problem:
                return problem
        return None

    return check_object


def _array_check(schema: dict[str, Any]) -> Any:
    """The check of an array's length and items, or None."""
    items = schema.get("items")
    item_check = _compile_walker(items) if isinstance(items, dict) else None
    min_items, max_items = schema.get("minItems"), schema.get("maxItems")
    if item_check is None and min_items is None and max_items is None:
        return None

    def check_array(v: Any, p: str) -> str | None:
        if not isinstance(v, list):
            return None
        if min_items is not None and len(v) < min_items:
            return f"{p}: {len(v)} items, fewer than {min_items}"
        if max_items is not None and len(v) > max_items:
            return f"{p}: {len(v)} items, more than {max_items}"
        if item_check is not None:
            for i, item in enumerate(v):
                problem = item_check(item, f"{p}[{i}]")
                if problem:
                    return problem
        return None

    return check_array

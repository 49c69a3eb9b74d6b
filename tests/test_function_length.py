"""No function of the package is over 60 lines of code and no module over 600 lines, but those listed with a reason.

Longer functions are split into named steps and longer modules along their seams. Where a split would make the
code worse, :data:`LONG_FUNCTIONS` or :data:`LONG_MODULES` names the function or module and says why.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "starlog"
MAX_LINES = 60
MODULE_LINES = 600

#: ``"starlog/path.py:function"`` (a method: ``Class.method``) → why it is one function of over MAX_LINES lines.
LONG_FUNCTIONS: dict[str, str] = {}

#: ``"starlog/path.py"`` → why it is one module of over MODULE_LINES lines.
LONG_MODULES: dict[str, str] = {}


def code_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from ``def`` to the function's last line, its docstring left out (decorators are not counted)."""
    assert function.end_lineno is not None
    lines = function.end_lineno - function.lineno + 1
    first = function.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        assert first.end_lineno is not None
        lines -= first.end_lineno - first.lineno + 1
    return lines


def _functions(tree: ast.AST, prefix: str = "") -> Iterator[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """Every function of ``tree`` (nested ones and methods too) with its qualified name (``Class.method``)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield f"{prefix}{node.name}", node
            yield from _functions(node, f"{prefix}{node.name}.")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, f"{prefix}{node.name}.")
        else:
            yield from _functions(node, prefix)


def long_functions(source: str, name: str) -> Iterator[str]:
    """``name:function`` for each function over :data:`MAX_LINES` lines of code."""
    for qualified, node in _functions(ast.parse(source)):
        if code_lines(node) > MAX_LINES:
            yield f"{name}:{qualified}"


def long_module(source: str, name: str) -> Iterator[str]:
    """``name`` when the module is over :data:`MODULE_LINES` lines."""
    if source.count("\n") > MODULE_LINES:
        yield name


def _sources() -> Iterator[tuple[str, str]]:
    for path in sorted(PACKAGE.rglob("*.py")):
        yield str(path.relative_to(PACKAGE.parent).as_posix()), path.read_text(encoding="utf-8")


def test_no_function_is_over_60_lines() -> None:
    found = [f for name, source in _sources() for f in long_functions(source, name)]
    unlisted = [f for f in found if f not in LONG_FUNCTIONS]
    assert not unlisted, f"functions over {MAX_LINES} lines of code (split them, or list them with the reason):\n" + \
        "\n".join(unlisted)
    assert not set(LONG_FUNCTIONS) - set(found), "listed, but no longer long: " + ", ".join(
        sorted(set(LONG_FUNCTIONS) - set(found)))


def test_no_module_is_over_600_lines() -> None:
    found = [m for name, source in _sources() for m in long_module(source, name)]
    unlisted = [m for m in found if m not in LONG_MODULES]
    assert not unlisted, f"modules over {MODULE_LINES} lines (split them, or list them with the reason):\n" + \
        "\n".join(unlisted)
    assert not set(LONG_MODULES) - set(found), "listed, but no longer long: " + ", ".join(
        sorted(set(LONG_MODULES) - set(found)))


def test_the_count_leaves_out_the_docstring_only() -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_LINES - 1))
    docstring = '    """What it does.\n\n    At length.\n    """\n'
    at_limit = f"def f():\n{docstring}{body}"
    assert not list(long_functions(at_limit, "m"))
    assert list(long_functions(at_limit + "    return x0\n", "m")) == ["m:f"]
    method = "class C:\n" + "".join(f"    {line}\n" for line in (at_limit + "    return x0\n").splitlines())
    assert list(long_functions(method, "m")) == ["m:C.f"]


def test_a_module_over_the_limit_is_found() -> None:
    assert not list(long_module('"""A module."""\n' + "x = 1\n" * (MODULE_LINES - 1), "m"))
    assert list(long_module('"""A module."""\n' + "x = 1\n" * MODULE_LINES, "m")) == ["m"]

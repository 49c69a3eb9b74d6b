"""No function of the package is over 100 lines of code, and no module over about 500 lines without a reason.

Longer functions are split into named steps; a longer module says in its docstring why it is one
module ("One module of over 500 lines: ...").
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "starlog"
MAX_LINES = 100
MODULE_LINES = 520
MODULE_REASON = "One module of over 500 lines:"


def code_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from ``def`` to the function's last line, its docstring left out (decorators are not counted)."""
    assert function.end_lineno is not None
    lines = function.end_lineno - function.lineno + 1
    first = function.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        assert first.end_lineno is not None
        lines -= first.end_lineno - first.lineno + 1
    return lines


def long_functions(source: str, name: str) -> Iterator[str]:
    """``name:line function (N lines)`` for each function (nested ones and methods too) over :data:`MAX_LINES`."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and code_lines(node) > MAX_LINES:
            yield f"{name}:{node.lineno} {node.name} ({code_lines(node)} lines)"


def test_no_function_is_over_100_lines() -> None:
    found = [line for path in sorted(PACKAGE.rglob("*.py"))
             for line in long_functions(path.read_text(encoding="utf-8"), str(path.relative_to(PACKAGE.parent)))]
    assert not found, "functions over 100 lines of code (split them):\n" + "\n".join(found)


def test_the_count_leaves_out_the_docstring_only() -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_LINES - 1))
    docstring = '    """What it does.\n\n    At length.\n    """\n'
    at_limit = f"def f():\n{docstring}{body}"
    assert not list(long_functions(at_limit, "m"))
    assert list(long_functions(at_limit + "    return x0\n", "m")) == ["m:1 f (101 lines)"]


def modules_without_reason(source: str, name: str) -> Iterator[str]:
    """``name (N lines)`` when the module is over :data:`MODULE_LINES` and its docstring gives no reason."""
    lines = source.count("\n")
    docstring = ast.get_docstring(ast.parse(source)) or ""
    if lines > MODULE_LINES and MODULE_REASON not in " ".join(docstring.split()):
        yield f"{name} ({lines} lines)"


def test_long_modules_say_why() -> None:
    found = [line for path in sorted(PACKAGE.rglob("*.py"))
             for line in modules_without_reason(path.read_text(encoding="utf-8"), str(path.relative_to(PACKAGE.parent)))]
    assert not found, f"modules over {MODULE_LINES} lines without '{MODULE_REASON} ...' in the docstring:\n" + "\n".join(found)


def test_a_long_module_needs_the_reason() -> None:
    body = "x = 1\n" * (MODULE_LINES + 1)
    assert list(modules_without_reason(f'"""A module."""\n{body}', "m")) == [f"m ({MODULE_LINES + 2} lines)"]
    assert not list(modules_without_reason(f'"""A module.\n\n{MODULE_REASON} one class."""\n{body}', "m"))

"""The shape of starlog's imports: no cycle among its modules (imports inside functions count), the layers that
must not import each other do not, and the CLI imports no private module or name.

The layers, one way: the algorithms (plain functions on numpy arrays) import neither the log container
(:mod:`starlog.io`) nor the stages (:mod:`starlog.stages`) nor the machinery that replays a log through a stage
(:mod:`starlog.replay`); the container imports neither of the last two, and that machinery no stage.

Every module is parsed with ``ast``; each ``import`` and ``from ... import`` (at the top, inside a
function or under ``if TYPE_CHECKING``) that names a ``starlog`` module is an edge. Importing
``a.c.y`` also runs the ``__init__`` of each package on its path that the importer is not itself
inside, so those packages are edges too (``a.b.x`` importing ``a.c.y`` runs ``a/c/__init__.py``).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _modules(root: Path, package: str) -> dict[str, tuple[Path, bool]]:
    """Dotted name → (file, is a package) of every module under ``root / package``."""
    found = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return found


def _ancestors(name: str) -> set[str]:
    parts = name.split(".")
    return {".".join(parts[:k]) for k in range(1, len(parts))}


def _imported(node: ast.AST, package: str, modules: dict[str, tuple[Path, bool]]) -> list[str]:
    """The names an import statement imports as modules (``from m import name``: ``m``, or ``m.name`` if a module)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        parts = package.split(".")
        base = parts[: len(parts) - node.level + 1]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    submodules = [f"{prefix}.{a.name}" for a in node.names if f"{prefix}.{a.name}" in modules]
    return submodules + ([prefix] if len(submodules) < len(node.names) else [])


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module → the modules of ``package`` it imports, anywhere in its code."""
    modules = _modules(root, package)
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        inside = _ancestors(name) | ({name} if is_package else set())
        own_package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            for target in _imported(node, own_package, modules):
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target:
                    graph[name] |= ({target} | (_ancestors(target) - inside)) - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, without recursion)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, edges = work[-1]
            child = next(edges, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def _describe(graph: dict[str, set[str]], component: list[str]) -> str:
    return "; ".join(f"{m} -> {', '.join(sorted(graph[m] & set(component)))}" for m in component)


#: The algorithm packages: plain functions on numpy arrays, which know nothing of logs.
ALGORITHMS = ("starlog.sim", "starlog.detect", "starlog.centroiding", "starlog.tracking", "starlog.platform_motion",
              "starlog.compensation", "starlog.attitude")
#: Each layer (packages or modules) → what it must not import, with why.
FORBIDDEN = [
    (ALGORITHMS, ("starlog.io", "starlog.stages", "starlog.replay"), "an algorithm imports the log layer or a stage"),
    (("starlog.io",), ("starlog.stages", "starlog.replay"), "the log container imports a stage"),
    (("starlog.replay",), ("starlog.stages",), "the machinery the stages share imports a stage"),
]


def _inside(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def layer_violations(graph: dict[str, set[str]], layer: tuple[str, ...], forbidden: tuple[str, ...]) -> list[str]:
    """``module -> imported`` for each module of ``layer`` that imports a module of ``forbidden``."""
    return [f"{name} -> {dep}" for name in sorted(graph) if _inside(name, layer)
            for dep in sorted(graph[name]) if _inside(dep, forbidden)]


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports(root: Path, package: str, layer: str) -> list[str]:
    """``file:line name`` for each import, in the modules of ``layer``, of a ``_``-prefixed module of ``package``
    or of a ``_``-prefixed name from one of its modules (dunder names such as ``__version__`` are public)."""
    found = []
    for name, (path, is_package) in sorted(_modules(root, package).items()):
        if not _inside(name, (layer,)):
            continue
        own_package = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                modules, names = [a.name for a in node.names], []
            elif isinstance(node, ast.ImportFrom):
                base = own_package.split(".")[: len(own_package.split(".")) - node.level + 1] if node.level else []
                modules = [".".join(base + ([node.module] if node.module else []))]
                names = [a.name for a in node.names]
            else:
                continue
            modules = [m for m in modules if m == package or m.startswith(package + ".")]
            private = [m for m in modules if any(_private(part) for part in m.split("."))]
            private += [f"{modules[0]}.{n}" for n in names if modules and _private(n)]
            found += [f"{path.relative_to(root)}:{node.lineno} {p}" for p in private]
    return found


def test_no_import_cycle_among_starlog_modules() -> None:
    graph = import_graph(ROOT, "starlog")
    assert len(graph) > 100
    found = cycles(graph)
    assert not found, "\n".join(_describe(graph, c) for c in found)


def test_the_reports_and_the_stage_declaration_import_only_downwards() -> None:
    graph = import_graph(ROOT, "starlog")
    report = {dep for name, deps in graph.items() if name.startswith("starlog.report") for dep in deps}
    assert not {d for d in report if d.startswith("starlog.experiment")}, "the report imports the experiment"
    assert not graph["starlog.replay.declaration"] & {"starlog.replay.plugins", "starlog.stage_api",
                                                      "starlog.stages.custom"}


def test_the_algorithms_know_no_log_and_the_log_container_no_stage() -> None:
    graph = import_graph(ROOT, "starlog")
    assert all(any(_inside(name, (p,)) for name in graph) for p in ALGORITHMS)
    found = [f"{why}: {line}" for layer, forbidden, why in FORBIDDEN
             for line in layer_violations(graph, layer, forbidden)]
    assert not found, "\n".join(found)


def test_the_cli_imports_no_private_module_or_name() -> None:
    found = private_imports(ROOT, "starlog", "starlog.cli")
    assert not found, "the CLI imports private names (make them public where they live):\n" + "\n".join(found)


def test_the_layer_check_finds_a_forbidden_import_through_a_package(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "algo").mkdir(parents=True)
    (tmp_path / "pkg" / "io").mkdir()
    for init in ("pkg", "pkg/algo", "pkg/io"):
        (tmp_path / init / "__init__.py").write_text("")
    (tmp_path / "pkg" / "io" / "reader.py").write_text("X = 1\n")
    (tmp_path / "pkg" / "algo" / "fit.py").write_text("def f():\n    from pkg.io.reader import X\n    return X\n")
    (tmp_path / "pkg" / "algo" / "plain.py").write_text("from pkg.algo import fit\n")
    graph = import_graph(tmp_path, "pkg")
    assert layer_violations(graph, ("pkg.algo",), ("pkg.io",)) == ["pkg.algo.fit -> pkg.io", "pkg.algo.fit -> pkg.io.reader"]
    assert layer_violations(graph, ("pkg.io",), ("pkg.algo",)) == []
    assert layer_violations(graph, ("pkg.alg",), ("pkg.io",)) == []  # a prefix is a package, not a string


def test_the_private_check_finds_private_modules_and_names(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "cli").mkdir(parents=True)
    (tmp_path / "pkg" / "__init__.py").write_text("__version__ = '1'\n")
    (tmp_path / "pkg" / "_lifeline.py").write_text("def die_of(): ...\n")
    (tmp_path / "pkg" / "pool.py").write_text("class _Pool: ...\nclass Pool: ...\n")
    (tmp_path / "pkg" / "cli" / "__init__.py").write_text(
        "from pkg import __version__\nfrom pkg._lifeline import die_of\nfrom pkg.pool import Pool, _Pool\n")
    (tmp_path / "pkg" / "cli" / "run.py").write_text("def f():\n    import pkg._lifeline\n    from .. import pool\n")
    (tmp_path / "pkg" / "other.py").write_text("from pkg.pool import _Pool\n")
    assert private_imports(tmp_path, "pkg", "pkg.cli") == [
        "pkg/cli/__init__.py:2 pkg._lifeline", "pkg/cli/__init__.py:3 pkg.pool._Pool", "pkg/cli/run.py:2 pkg._lifeline"]


def test_the_check_finds_a_cycle_through_a_function_local_import(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "sub" / "__init__.py").write_text("from pkg.sub.b import B\n")
    (tmp_path / "pkg" / "a.py").write_text("def f():\n    from pkg.sub import b\n    return b\n")
    (tmp_path / "pkg" / "sub" / "b.py").write_text("from . import c\nB = 1\n")
    (tmp_path / "pkg" / "sub" / "c.py").write_text("from pkg import a\n")
    (tmp_path / "pkg" / "d.py").write_text("import pkg.a\n")
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.a"] == {"pkg.sub", "pkg.sub.b"} and graph["pkg.d"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.sub", "pkg.sub.b", "pkg.sub.c"]]


def test_codecs_import_neither_io_nor_stages() -> None:
    graph = import_graph(ROOT, "starlog")
    codecs = [name for name in graph if name == "starlog.codecs" or name.startswith("starlog.codecs.")]
    assert len(codecs) > 10
    layers = ("starlog.io", "starlog.stages")
    found = {name: sorted(d for d in graph[name] if any(d == p or d.startswith(p + ".") for p in layers))
             for name in codecs}
    assert not {name: deps for name, deps in found.items() if deps}, "codecs import the container or a stage"


# ---------------------------------------------------------------- private names stay in their module

#: Private modules other modules still import, each with the branch that makes it public (the lead empties this
#: list when the branches are merged): a ``_``-prefixed name or module is its own module's business.
PRIVATE_CROSSINGS_LEFT: dict[str, str] = {}


def _private(dotted: str) -> bool:
    return any(part.startswith("_") and not part.startswith("__") for part in dotted.split("."))


def private_crossings(root: Path, package: str) -> list[str]:
    """``module:line target`` for each import of a ``_``-prefixed module or name from another module of ``package``,
    and each ``m._name`` read from a module ``m`` of the package that the module imported."""
    modules = _modules(root, package)
    found = []
    for name, (path, is_package) in modules.items():
        own_package = name if is_package else name.rpartition(".")[0]
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        bound: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [(alias.name, alias.asname) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                parts = own_package.split(".")
                base = parts[: len(parts) - node.level + 1] if node.level else []
                prefix = ".".join(base + ([node.module] if node.module else []))
                targets = [(f"{prefix}.{alias.name}", alias.asname or alias.name) for alias in node.names]
            else:
                continue
            for target, alias in targets:
                if target.split(".")[0] != package:
                    continue
                if _private(target):
                    found.append(f"{name}:{node.lineno} {target}")
                if target in modules and alias:
                    bound[alias] = target
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
                    and _private(node.attr)):
                found.append(f"{name}:{node.lineno} {bound[node.value.id]}.{node.attr}")
    return found


def test_no_private_name_crosses_modules() -> None:
    crossings = private_crossings(ROOT, "starlog")

    def left_for(line: str) -> str | None:
        target = line.split()[1]
        return next((left for left in PRIVATE_CROSSINGS_LEFT if target == left or target.startswith(f"{left}.")), None)

    found = [line for line in crossings if left_for(line) is None]
    assert not found, "private names used by another module (make them public, named for what they are):\n" + \
        "\n".join(found)
    stale = set(PRIVATE_CROSSINGS_LEFT) - {left_for(line) for line in crossings}
    assert not stale, f"no longer imported by another module, take them off PRIVATE_CROSSINGS_LEFT: {sorted(stale)}"


def test_the_private_name_check_finds_each_form(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / "pkg" / "__init__.py").write_text("from pkg.sub._hidden import thing\n")
    (tmp_path / "pkg" / "sub" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "sub" / "_hidden.py").write_text("thing = 1\n")
    (tmp_path / "pkg" / "sub" / "open.py").write_text("_secret = 2\nshown = 3\n")
    (tmp_path / "pkg" / "sub" / "user.py").write_text(
        "from . import open\nfrom .open import _secret, shown\nimport pkg.sub.open as o\n"
        "def f():\n    return open._secret + o._secret + o.shown + shown + _secret\n")
    assert sorted(private_crossings(tmp_path, "pkg")) == [
        "pkg.sub.user:2 pkg.sub.open._secret", "pkg.sub.user:5 pkg.sub.open._secret",
        "pkg.sub.user:5 pkg.sub.open._secret", "pkg:1 pkg.sub._hidden.thing"]

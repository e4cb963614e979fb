"""The package's layers: data flow one way, a lower layer never imports a higher one, and the modules of a
package never import each other round a circle (imports inside functions counted).

Model specification → filters → likelihood and estimator (estimate) → results' uses (uncertainty,
validation, design, reports) → what users hold (``greyid.api``: `Model` and `FitResult` with the calls
that reach those layers) → ready models and data sets, fleets, populations → command line.  No
import points upward, at module level or inside a function.
"""

from __future__ import annotations

import ast
from pathlib import Path

SOURCE = Path(__file__).resolve().parents[1] / "src" / "greyid"

#: Each package's layer; a module may import from its own layer and those below.
LAYERS = {
    "errors": 0, "schema": 0, "outputs": 0, "progress": 0, "runtime": 0,
    "scaled": 1, "data": 1,
    "model": 2,
    "filters": 3,
    "estimate": 4, "simulate": 4,
    "uncertainty": 5, "validation": 5, "design": 5,
    "report": 6,
    "api": 7,
    "library": 8, "datasets": 8,
    "fleet": 9,
    "population": 10,
    "cli": 11, "__main__": 11,
}


def _module(path: Path, source: Path) -> str:
    parts = ["greyid", *path.relative_to(source).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _target(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _package(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None  # None: the root package (greyid.__version__ and the like)


def _imports(tree: ast.Module):
    """``(import node, enclosing class or None, at module level)`` for every ``from`` import."""
    def visit(node, cls, top):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ImportFrom):
                yield child, cls, top
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, child.name, top)
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                yield from visit(child, cls, False)
            else:
                yield from visit(child, cls, top)
    yield from visit(tree, None, True)


def upward_imports(source: Path = SOURCE) -> list[str]:
    """Every import of a higher layer's package, at module level or inside a function."""
    found = []
    for path in sorted(source.rglob("*.py")):
        module = _module(path, source)
        package = _package(module)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node, cls, top in _imports(tree):
            imported = _target(module, path.name == "__init__.py", node)
            target = _package(imported)
            if package is None or target is None or not imported.startswith("greyid"):
                continue
            if LAYERS[target] <= LAYERS[package]:
                continue
            found.append(f"{module} ({'module level' if top else 'in ' + (cls or 'a function')}) imports "
                         f"greyid.{target}")
    return found


def test_every_package_has_a_layer():
    packages = {path.relative_to(SOURCE).parts[0].removesuffix(".py") for path in SOURCE.glob("*")
                if path.suffix == ".py" or (path.is_dir() and (path / "__init__.py").exists())}
    assert packages - {"__init__"} <= set(LAYERS), packages - set(LAYERS)


def test_no_lower_layer_imports_a_higher_one():
    assert upward_imports() == []


def test_the_check_sees_an_upward_import(tmp_path):
    """The check itself: an upward import written into a copy of a lower module is found."""
    import shutil

    copy = tmp_path / "greyid"
    shutil.copytree(SOURCE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / "filters" / "api.py"
    target.write_text(target.read_text(encoding="utf-8") + "\n\ndef helper():\n    from ..report import html\n",
                      encoding="utf-8")
    assert upward_imports(copy) == ["greyid.filters.api (in a function) imports greyid.report"]


def module_imports(source: Path = SOURCE) -> dict[str, set[str]]:
    """Module → the greyid modules it imports, at module level or inside functions."""
    graph: dict[str, set[str]] = {}
    for path in sorted(source.rglob("*.py")):
        module = _module(path, source)
        edges = graph.setdefault(module, set())
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node, _, _ in _imports(tree):
            imported = _target(module, path.name == "__init__.py", node)
            if not imported.startswith("greyid"):
                continue
            for alias in node.names:  # ``from . import laplace`` imports the module greyid.population.laplace
                candidate = f"{imported}.{alias.name}"
                relative = Path(*candidate.split(".")[1:])
                if (source / relative).with_suffix(".py").exists() or (source / relative / "__init__.py").exists():
                    edges.add(candidate)
                else:
                    edges.add(imported)
    return graph


def circles_inside_packages(source: Path = SOURCE) -> list[list[str]]:
    """Groups of modules of one package that import each other round a circle (Tarjan's components)."""
    def package(module: str) -> str:
        return module.rsplit(".", 1)[0] if module.count(".") >= 2 else "greyid"

    graph = {m: {t for t in targets if t != m and package(t) == package(m)}
             for m, targets in module_imports(source).items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return circles


def test_no_package_has_modules_that_import_each_other_round_a_circle():
    assert circles_inside_packages() == []


def test_the_check_sees_a_circle_through_an_import_inside_a_function(tmp_path):
    import shutil

    copy = tmp_path / "greyid"
    shutil.copytree(SOURCE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    target = copy / "filters" / "steady.py"  # the driver and the Kalman filter import steady: back closes a circle
    target.write_text(target.read_text(encoding="utf-8") + "\n\ndef helper():\n    from .driver import scan_rows\n",
                      encoding="utf-8")
    expected = ["greyid.filters.driver", "greyid.filters.kalman", "greyid.filters.steady"]
    assert circles_inside_packages(copy) == [expected]

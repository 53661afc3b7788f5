"""The stages import downwards only (docs/development.md "Layers"), imports inside functions counted.

Every ``import``/``from ... import`` of ``depthgt`` anywhere in ``src/depthgt`` (module
level, inside functions, under ``TYPE_CHECKING``) is read from the source with ``ast``
(nothing is imported, so the test is fast and torch-free) and checked against
:data:`LAYERS`, lowest first:

* leaves: the top-level modules (errors, io, geometry, atomic, device, registry,
  status, the metric vocabulary, the depth operators, ...) import only leaves;
* sources/synth: the adapters and the synthetic scenes read no settings;
* settings: every stage's settings module, wherever it sits (``gt/render/settings.py``,
  ``registration/settings.py``, ...: :data:`SETTINGS_MODULES`), the registry of
  registration methods they check names against, and the builder ``depthgt.settings``
  that imports them all. They are one unit: torch-free, importing only leaves,
  sources/synth (``sources.base.check_options``) and each other, so that the builder
  and any stage may import them;
* registration -> gt -> data (the torch Dataset over the manifests) -> enhance -> eval
  -> jobs/cli.

Within a unit no two modules import each other, directly or through others
(:func:`module_cycle`).

A unit (a top-level module, or a subpackage such as ``depthgt.gt``) may import units of
its own layer or lower, and the graph of units has no cycle. Edges that still point
upwards are listed in :data:`KNOWN_VIOLATIONS`; the test fails when one of them is gone
too (delete it from the list), so the list only shrinks.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "depthgt"

#: Modules of the settings layer besides every module named ``settings`` (a stage's
#: settings beside the stage): the registration methods' registry, whose names and
#: properties the registration settings ask.
SETTINGS_MODULES = frozenset({"depthgt.registration.methods"})

# units by layer, lowest first; a top-level module not named here is a leaf
LAYERS: tuple[tuple[str, frozenset[str]], ...] = (
    ("leaves", frozenset()),  # every top-level module but settings and cli
    ("sources/synth", frozenset({"depthgt.sources", "depthgt.synth"})),
    ("settings", frozenset({"depthgt.settings"})),
    ("registration", frozenset({"depthgt.registration"})),
    ("gt", frozenset({"depthgt.gt"})),
    ("data", frozenset({"depthgt.data"})),
    ("enhance", frozenset({"depthgt.enhance"})),
    ("eval", frozenset({"depthgt.eval"})),
    ("jobs/cli", frozenset({"depthgt.jobs", "depthgt.cli"})),
)

# (importing module, imported module) edges that still point upwards: none is left (the
# soft splat, the rasteriser and the sensor-noise law became the leaves
# depthgt.splatting, depthgt.rasterise and depthgt.noise_law). An entry added here
# must name an edge that exists, and goes when the edge goes.
KNOWN_VIOLATIONS: frozenset[tuple[str, str]] = frozenset()


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (SRC / rel).with_suffix(".py").is_file() or (SRC / rel / "__init__.py").is_file()


def internal_imports(path: Path, name: str | None = None) -> list[tuple[str, int]]:
    """(imported depthgt module, line) of every import in ``path`` (the module ``name``),
    at any depth."""
    name = name or module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names if alias.name.split(".")[0] == "depthgt"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "depthgt":
                continue
            for alias in node.names:  # `from depthgt.gt import store` imports the module depthgt.gt.store
                sub = f"{target}.{alias.name}"
                found.append((sub if is_module(sub) else target, node.lineno))
    return found


def unit_of(module: str) -> str:
    """The top-level module or the subpackage a module belongs to; every module of the
    settings layer belongs to ``depthgt.settings``."""
    if module.rsplit(".", 1)[-1] == "settings" or module in SETTINGS_MODULES:
        return "depthgt.settings"
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else module


def layer_of(unit: str) -> int:
    for rank, (_, units) in enumerate(LAYERS):
        if unit in units:
            return rank
    if unit == "depthgt" or (PACKAGE / f"{unit.split('.')[1]}.py").is_file():
        return 0  # a leaf
    raise AssertionError(f"{unit} has no layer: add it to LAYERS in tests/test_layers.py")


def all_edges() -> list[tuple[str, str, str]]:
    """(importing module, imported module, "file:line") of every internal import."""
    edges = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for target, line in internal_imports(path):
            edges.append((module_name(path), target, f"{path.relative_to(SRC.parent)}:{line}"))
    return edges


def upward(edges) -> dict[tuple[str, str], list[str]]:
    found: dict[tuple[str, str], list[str]] = {}
    for src, dst, where in edges:
        if layer_of(unit_of(dst)) > layer_of(unit_of(src)):
            found.setdefault((src, dst), []).append(where)
    return found


def first_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """The first cycle a depth-first search of ``graph`` (node -> the nodes it imports)
    meets, as the nodes along it with the first repeated at the end, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        path.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return path[path.index(v) :] + [v]
            if v not in state and (found := visit(v)):
                return found
        path.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (found := visit(u)):
            return found
    return None


def cycle(edges) -> list[str] | None:
    """A cycle in the graph of units (self-loops and known violations left out), or None."""
    graph: dict[str, set[str]] = {}
    for src, dst, _ in edges:
        a, b = unit_of(src), unit_of(dst)
        if a != b and (src, dst) not in KNOWN_VIOLATIONS:
            graph.setdefault(a, set()).add(b)
    return first_cycle(graph)


def test_every_internal_import_names_a_module():
    missing = [f"{where}: {dst}" for _, dst, where in all_edges() if not is_module(dst)]
    assert not missing, "imports of depthgt modules that do not exist:\n" + "\n".join(missing)


def test_every_module_has_a_layer():
    for path in PACKAGE.rglob("*.py"):
        layer_of(unit_of(module_name(path)))


def test_stages_import_downwards_only():
    found = upward(all_edges())
    new = {edge: where for edge, where in found.items() if edge not in KNOWN_VIOLATIONS}
    assert not new, (
        'upward imports (docs/development.md "Layers"; move the shared part to a leaf below both):\n'
        + "\n".join(
            f"{', '.join(where)}: {src} ({LAYERS[layer_of(unit_of(src))][0]}) imports {dst} "
            f"({LAYERS[layer_of(unit_of(dst))][0]})"
            for (src, dst), where in sorted(new.items())
        )
    )


def test_known_violations_are_still_there():
    found = upward(all_edges())
    gone = sorted(KNOWN_VIOLATIONS - set(found))
    assert not gone, f"no longer imported upwards: delete from KNOWN_VIOLATIONS: {gone}"


def test_no_cycle_between_packages():
    found = cycle(all_edges())
    assert found is None, "import cycle between units: " + " -> ".join(found)


def module_cycle(edges) -> list[str] | None:
    """A cycle in the graph of modules (imports at any depth, ``TYPE_CHECKING`` ones
    included), or None: two modules of one package that import each other, directly or
    through others, hold a circle open even where a function-level import lets it load."""
    graph: dict[str, set[str]] = {}
    for src, dst, _ in edges:
        if src != dst:
            graph.setdefault(src, set()).add(dst)
    return first_cycle(graph)


def test_no_cycle_between_modules():
    found = module_cycle(all_edges())
    assert found is None, "import cycle between modules: " + " -> ".join(found)


def test_the_module_cycle_check_sees_a_circle_inside_a_package(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("from depthgt.gt import coverage\n")
    b.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from depthgt.gt.build import x\n")
    edges = [("depthgt.gt.build", dst, f"a.py:{line}") for dst, line in internal_imports(a, "depthgt.gt.build")]
    edges += [("depthgt.gt.coverage", dst, f"b.py:{line}") for dst, line in internal_imports(b, "depthgt.gt.coverage")]
    assert cycle(edges) is None  # one unit: the package check does not see it
    assert module_cycle(edges) == ["depthgt.gt.build", "depthgt.gt.coverage", "depthgt.gt.build"]


def test_the_checker_sees_imports_inside_functions(tmp_path):
    fake = tmp_path / "fake.py"
    fake.write_text("def f():\n    from depthgt.eval import metrics\n")
    edges = [("depthgt.gt.fake", dst, f"fake.py:{line}") for dst, line in internal_imports(fake, "depthgt.gt.fake")]
    assert edges == [("depthgt.gt.fake", "depthgt.eval.metrics", "fake.py:2")]
    assert set(upward(edges)) == {("depthgt.gt.fake", "depthgt.eval.metrics")}


#: A function in src longer than this (lines, docstring included) says why in its
#: docstring (issue 28): "long because ...", "longer than ..." or "long for its docstring".
MAX_FUNCTION_LINES = 80
LENGTH_REASONS = ("long because", "longer than", "long for its docstring")


def long_functions(path: Path, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int, bool]]:
    """(name, lines, whether its docstring gives a reason) of the functions of ``path``
    longer than ``limit`` lines."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines = node.end_lineno - node.lineno + 1
            if lines > limit:
                doc = (ast.get_docstring(node) or "").lower()
                found.append((node.name, lines, any(r in doc for r in LENGTH_REASONS)))
    return found


def test_long_functions_say_why(tmp_path):
    silent = [
        f"{path.relative_to(SRC)}: {name} ({lines} lines)"
        for path in sorted(PACKAGE.rglob("*.py"))
        for name, lines, why in long_functions(path)
        if not why
    ]
    assert not silent, (
        f"functions over {MAX_FUNCTION_LINES} lines without a reason in their docstring (split them, or say "
        f"'long because ...'):\n" + "\n".join(silent)
    )
    fake = tmp_path / "fake.py"
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES))
    fake.write_text(f'def f():\n    """Short."""\n{body}\n\ndef g():\n    """Long because."""\n{body}')
    assert long_functions(fake) == [("f", MAX_FUNCTION_LINES + 2, False), ("g", MAX_FUNCTION_LINES + 2, True)]

"""Every third-party module that the package, its workflow scripts, the tests and the
benchmarks import is declared in pyproject.toml (a fresh virtual environment with the
README's command has it), and the lock file pins what the README installs."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# import name -> distribution name, where the two differ
DISTRIBUTION_OF = {
    "cv2": "opencv-python-headless",
    "yaml": "pyyaml",
    "PIL": "pillow",
    "OpenEXR": "openexr",
    "Imath": "openexr",
    "sklearn": "scikit-learn",
    "skimage": "scikit-image",
    "attr": "attrs",
    "dateutil": "python-dateutil",
}
# libraries that pandas (and others) import on demand for a call, with the code that needs them
USED_THROUGH = {
    "pyarrow": re.compile(r"\.(to|read)_parquet\("),
    "tabulate": re.compile(r"\.to_markdown\("),
    "scipy": re.compile(r"method\s*=\s*[\"'](spearman|kendall)[\"']"),
}
# where the code lives -> which requirement sets may provide its imports
SCOPES = {
    "src": ("dependencies", "bench"),  # bench: Open3D, imported only when installed (RDE backend)
    "workflow": ("dependencies",),
    "tests": ("dependencies", "test"),
    "bench": ("dependencies", "test", "bench"),
}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(req: str) -> str:
    return _norm(re.match(r"\s*([A-Za-z0-9_.-]+)", req).group(1))


def declared() -> dict[str, set[str]]:
    """Distribution names of pyproject.toml: ``dependencies`` and each optional extra."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    out = {"dependencies": {_requirement_name(r) for r in project["dependencies"]}}
    for extra, reqs in project.get("optional-dependencies", {}).items():
        out[extra] = {_requirement_name(r) for r in reqs}
    return out


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every absolute import in a file, also inside functions."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def third_party(path: Path) -> set[str]:
    """The imports of ``path`` that are neither the standard library, depthgt, nor a
    module beside it (the tests' helpers, bench's own modules); plus the libraries its
    code needs through another one (:data:`USED_THROUGH`)."""
    local = {p.stem for p in path.parent.glob("*.py")} | {"depthgt"}
    mods = {m for m in imported_modules(path) if m not in sys.stdlib_module_names and m not in local}
    text = path.read_text()
    mods |= {m for m, pattern in USED_THROUGH.items() if pattern.search(text)}
    return mods


def distribution(module: str) -> str:
    if module in DISTRIBUTION_OF:
        return _norm(DISTRIBUTION_OF[module])
    installed = metadata.packages_distributions().get(module)
    return _norm(installed[0]) if installed else _norm(module)


def undeclared(root: Path, scope: tuple[str, ...], requirements: dict[str, set[str]]) -> list[str]:
    allowed = set().union(*(requirements.get(s, set()) for s in scope))
    missing = []
    for path in sorted(root.rglob("*.py")):
        for module in sorted(third_party(path)):
            if distribution(module) not in allowed:
                missing.append(f"{path.relative_to(REPO)}: {module} (distribution {distribution(module)}) "
                               f"is in none of {', '.join(scope)} of pyproject.toml")
    return missing


@pytest.mark.parametrize("where", sorted(SCOPES))
def test_every_import_is_declared(where):
    missing = undeclared(REPO / where, SCOPES[where], declared())
    assert not missing, "undeclared imports:\n" + "\n".join(missing)


def test_the_check_finds_an_undeclared_import(tmp_path):
    (tmp_path / "helper.py").write_text("X = 1\n")
    (tmp_path / "mod.py").write_text(
        "import os\nimport helper\nfrom depthgt import io\n\ndef f(t):\n    import sklearn.linear_model  # heavy\n"
        "    return t.corr(t, method='spearman')\n")
    assert third_party(tmp_path / "mod.py") == {"sklearn", "scipy"}
    req = {"dependencies": {"numpy"}}
    assert distribution("sklearn") == "scikit-learn" and distribution("cv2") == "opencv-python-headless"
    missing = undeclared(tmp_path, ("dependencies",), req)
    assert len(missing) == 2 and "sklearn (distribution scikit-learn)" in missing[1]


def test_lock_file_pins_what_the_readme_installs():
    """constraints.txt pins one version of every distribution declared for the README's
    two commands (torch as pyproject pins it), and both commands use it."""
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not pinned with =="
            pins[_norm(name)] = version
    requirements = declared()
    for name in requirements["dependencies"] | requirements["test"]:
        assert name in pins, f"constraints.txt has no pin of {name} (pyproject.toml)"
    assert pins["torch"].split("+")[0] == "2.13.0"
    setup = (REPO / "README.md").read_text().split("## Set-up", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"```bash\n(.*?)```", setup, re.S)
    assert len(commands) == 2 and all("-c constraints.txt" in c for c in commands), commands

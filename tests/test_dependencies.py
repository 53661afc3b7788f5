"""Every third-party module that the package, its workflow scripts, the tests and the
benchmarks import is declared in pyproject.toml (a fresh virtual environment with the
README's command has it), and the lock file pins what the README installs."""

from __future__ import annotations

import ast
import functools
import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# import name -> distribution name, where the two differ
DISTRIBUTION_OF = {
    "cv2": "opencv-contrib-python-headless",  # the contrib build (cv2.ximgproc), pyproject.toml
    "yaml": "pyyaml",
    "PIL": "pillow",
    "OpenEXR": "openexr",
    "Imath": "openexr",
    "sklearn": "scikit-learn",
    "skimage": "scikit-image",
    "attr": "attrs",
    "dateutil": "python-dateutil",
}
# libraries that pandas imports on demand, by the method called: (method, its `method=`
# argument or None for any) -> the module
USED_THROUGH = {
    ("to_parquet", None): "pyarrow",
    ("read_parquet", None): "pyarrow",
    ("to_markdown", None): "tabulate",
    ("corr", "spearman"): "scipy",
    ("corr", "kendall"): "scipy",
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
    """Top-level names of every absolute import in a file, also inside functions, and
    the modules its calls need through pandas (:data:`USED_THROUGH`)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            method = next(
                (k.value.value for k in node.keywords if k.arg == "method" and isinstance(k.value, ast.Constant)), None
            )
            for key in ((node.func.attr, None), (node.func.attr, method)):
                if key in USED_THROUGH:
                    names.add(USED_THROUGH[key])
    return names


def third_party(path: Path) -> set[str]:
    """The imports of ``path`` that are neither the standard library, depthgt, nor a
    module of its folder or of tests/ (the tests' helpers, bench's own modules)."""
    local = {p.stem for p in (*path.parent.glob("*.py"), *(REPO / "tests").glob("*.py"))} | {"depthgt"}
    return {m for m in imported_modules(path) if m not in sys.stdlib_module_names and m not in local}


@functools.cache
def _installed() -> dict[str, list[str]]:
    return metadata.packages_distributions()


def distribution(module: str) -> str:
    """The distribution that provides ``module``: the table above, the installed
    packages' metadata, else the module's own name."""
    if module in DISTRIBUTION_OF:
        return _norm(DISTRIBUTION_OF[module])
    installed = _installed().get(module)
    return _norm(installed[0]) if installed else _norm(module)


def undeclared(root: Path, scope: tuple[str, ...], requirements: dict[str, set[str]]) -> list[str]:
    allowed = set().union(*(requirements.get(s, set()) for s in scope))
    missing = []
    for path in sorted(root.rglob("*.py")):
        for module in sorted(third_party(path)):
            if distribution(module) not in allowed:
                missing.append(
                    f"{path.relative_to(root.parent)}: {module} (distribution {distribution(module)}) "
                    f"is in none of {', '.join(scope)} of pyproject.toml"
                )
    return missing


@pytest.mark.parametrize("where", sorted(SCOPES))
def test_every_import_is_declared(where):
    missing = undeclared(REPO / where, SCOPES[where], declared())
    assert not missing, "undeclared imports:\n" + "\n".join(missing)


def test_the_check_finds_an_undeclared_import(tmp_path):
    (tmp_path / "helper.py").write_text("X = 1\n")
    (tmp_path / "mod.py").write_text(
        "import os\nimport helper\nfrom depthgt import io\n\ndef f(t):\n    import sklearn.linear_model  # heavy\n"
        "    return t.corr(t, method='spearman')\n"
    )
    assert third_party(tmp_path / "mod.py") == {"sklearn", "scipy"}
    req = {"dependencies": {"numpy"}}
    assert distribution("sklearn") == "scikit-learn" and distribution("cv2") == "opencv-contrib-python-headless"
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

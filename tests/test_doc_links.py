"""Every reference to a file or a section of this repository, in the code, the workflow,
the configs, the benchmarks, the tests and the docs, names one that exists.

A reference is
  * a markdown link ``[text](path)`` or ``[text](path#anchor)`` in a ``.md`` file
    (relative to the page; the anchor is a heading's GitHub slug);
  * a repository path in running text: one under a top-level folder (``docs/method.md``,
    ``bench/bench_real.py``, ``workflow/rules/common.smk``), a capitalised ``*.md`` name
    (``README.md``, ``DESIGN.md``: beside the citing file, else at the root), and
    ``README`` and ``bench/README`` for their ``.md``;
  * the sections quoted after such a path: ``docs/method.md "Registration checks"``,
    ``[method.md](method.md) "Registration checks"``, ``bench/README.md, sections "A" and
    "B"``, ``README ("Which poses")``. Each is a heading of that file (its trailing
    parenthesis may be left out) or the bold run-in title of one of its paragraphs
    (``**Which poses.** ...``).
Comment markers and line breaks are read through, so a wrapped reference counts. Not
references: paths with placeholders (``bench/NAME.py``, ``results/{model}/``), lower-case
bare names (outputs such as ``card.md``), and ```` ```python ```` examples of files to write.

And the renderer's settings table in docs/gt-renderer.md lists every ``render`` key with
the default the code has."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: the files whose references are checked (globs relative to the repository)
SCANNED = (
    "README.md",
    "pyproject.toml",
    "Snakefile",
    ".ci/run",
    "src/**/*.py",
    "workflow/**/*",
    "config/**/*.yaml",
    "profiles/**/*.yaml",
    "cluster/*",
    "bench/*.py",
    "bench/README.md",
    "docs/*.md",
    "tests/*.py",
)
#: this file's own examples are not references
NOT_SCANNED = ("tests/test_doc_links.py",)

#: the repository's top-level folders: a path in text that starts with one is a repository path
TOP = ("docs", "bench", "tests", "workflow", "config", "src", "cluster", "profiles", ".ci")
#: upper-case names that are documents, not placeholders such as NAME or WORKDIR
DOC_NAMES = ("README", "DESIGN", "STYLE", "CHANGELOG", "CONTRIBUTING", "LICENSE")

_TOP = "|".join(re.escape(t) for t in TOP)
_PATH = rf"(?:\.\./)*(?:(?:{_TOP})/[\w./-]*[\w-]|[A-Z][A-Z_]*\.md\b|(?:bench/)?README\b)"
_QUOTED = r'"([^"\n]{1,160})"'
_REF = re.compile(
    rf"(?<![\w./{{<$-])(?P<path>{_PATH})(?P<link>\]\([^)\s]*\))?"
    rf"(?:[ ,(]+(?:sections? )?{_QUOTED}(?P<more>(?:(?:,| and|, and) {_QUOTED})*))?"
)
_LINK = re.compile(r"\[[^\]\n]*\]\(([^)\s]+)\)")
_HEADING = re.compile(r"^#{1,6} +(.+?) *#*$", re.M)
_RUN_IN = re.compile(r"^(?:[*-] )?\*\*(.+?)\*\*", re.M)
_FENCE = re.compile(r"^```.*?^```", re.M | re.S)
_PYTHON_FENCE = re.compile(r"^ *```python$.*?^ *```$", re.M | re.S)


def scanned_files(repo: Path = REPO) -> list[Path]:
    files = set()
    for pattern in SCANNED:
        files.update(p for p in repo.glob(pattern) if p.is_file() and "__pycache__" not in p.parts)
    return sorted(p for p in files if str(p.relative_to(repo)) not in NOT_SCANNED)


def flattened(path: Path) -> str:
    """The file as running text on one line: comment markers and indentation dropped, so
    that a reference wrapped over lines of a comment or a docstring reads as one."""
    text = path.read_text(errors="replace")
    if path.suffix == ".md":
        lines = _PYTHON_FENCE.sub("", text).splitlines()
    else:
        lines = [re.sub(r"^\s*(?:#+:?)?\s?", "", line) for line in text.splitlines()]
    return " ".join(line.strip() for line in lines)


def _plain(text: str) -> str:
    """A heading or a quoted name as compared: no markdown, case, final stop or colon."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"[`*_]", "", text)
    return re.sub(r"\s+", " ", text).strip().rstrip(".:").strip().lower()


def slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def sections(page: Path) -> set[str]:
    """The names a quoted reference to ``page`` may use: its headings (with and without a
    trailing parenthesis) and its paragraphs' bold run-in titles."""
    text = _FENCE.sub("", page.read_text())
    names = {_plain(t) for t in _RUN_IN.findall(text)}
    for heading in _HEADING.findall(text):
        names |= {_plain(heading), _plain(re.sub(r"\s*\([^()]*\)$", "", heading))}
    return names


def anchors(page: Path) -> set[str]:
    return {slug(h) for h in _HEADING.findall(_FENCE.sub("", page.read_text()))}


def resolve(target: str, source: Path, repo: Path = REPO) -> Path | None:
    """The file of the repository that ``target`` names, cited from ``source``: a path
    under a top-level folder from the root, else beside ``source`` first; None when the
    repository has no such file."""
    if target in ("README", "bench/README"):
        target += ".md"
    candidates = [repo / target, source.parent / target]
    if not target.startswith(TOP):
        candidates.reverse()
    for c in candidates:
        c = c.resolve()
        if c.exists() and (c == repo or repo in c.parents):
            return c
    return None


def _placeholder(path: str) -> bool:
    """A path standing for many files: ``bench/NAME.py``, ``results/{model}/``, ``WORKDIR/x``."""
    if re.search(r"[{}<>*]", path):
        return True
    return any(
        re.fullmatch(r"[A-Z][A-Z_]*", part.split(".")[0]) and part.split(".")[0] not in DOC_NAMES
        for part in path.split("/")
    )


def references(path: Path) -> list[tuple[str, list[str]]]:
    """(target, section names) of every reference in ``path``; a link's anchor is the
    section ``#slug``."""
    text = flattened(path)
    refs = []
    if path.suffix == ".md":
        for target in _LINK.findall(text):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            refs.append((file or path.name, [f"#{anchor}"] if anchor else []))
    for m in _REF.finditer(text):
        target = m.group("link")[2:-1].partition("#")[0] if m.group("link") else m.group("path").rstrip(".")
        if _placeholder(target):
            continue
        names = [m.group(3)] if m.group(3) else []
        refs.append((target, names + re.findall(_QUOTED, m.group("more") or "")))
    return refs


def problems(repo: Path = REPO) -> list[str]:
    """One line per reference to a file or section that ``repo`` does not have."""
    found = []
    for path in scanned_files(repo):
        rel = path.relative_to(repo)
        for target, names in references(path):
            file = path if target == path.name else resolve(target, path, repo)
            if file is None:
                found.append(f"{rel}: {target} is not a file of the repository")
                continue
            if names and file.suffix != ".md":
                found.append(f"{rel}: {target} {names}: sections of a file that is not markdown")
                continue
            for name in names:
                if name.startswith("#"):
                    if name[1:] not in anchors(file):
                        found.append(f"{rel}: {target}{name}: no such heading")
                elif _plain(name) not in sections(file):
                    found.append(f'{rel}: {target} "{name}": no such section')
    return found


def test_every_reference_names_an_existing_file_and_section():
    found = problems()
    assert not found, f"{len(found)} references to missing files or sections:\n" + "\n".join(found)


def test_the_reader_finds_each_kind_of_broken_reference(tmp_path):
    """The check itself, on a repository of three files: every form of reference is read
    (wrapped in a comment, a link with an anchor, a link then a section, several sections,
    README without .md), and each broken one is reported; placeholders are not references."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "src").mkdir()
    (tmp_path / "README.md").write_text("# Top\n\n**Which poses.** Text.\n\n## Set-up\n")
    (tmp_path / "docs" / "a.md").write_text(
        "# A\n\n## Registration checks\n\nSee [top](../README.md#set-up), [top](../README.md#gone),\n"
        '[b](b.md), README "Which poses", ../README.md, sections "Set-up" and "Missing one".\n'
        "Also bench/NAME.py and results/{model}/best.pt and card.md.\n\n"
        "```python\n# src/new_module.py\n```\n"
    )
    (tmp_path / "src" / "m.py").write_text(
        '"""See docs/a.md "Registration\n    checks" and docs/a.md "Registration\n    gone".\n"""\n'
        '# as DESIGN.md "Layers" has it (docs/a.md)\n'
    )
    assert sorted(problems(tmp_path)) == sorted(
        [
            "docs/a.md: ../README.md#gone: no such heading",
            "docs/a.md: b.md is not a file of the repository",
            'docs/a.md: ../README.md "Missing one": no such section',
            'src/m.py: docs/a.md "Registration gone": no such section',
            "src/m.py: DESIGN.md is not a file of the repository",
        ]
    )


def test_the_renderer_page_lists_every_render_setting_with_its_default():
    """docs/gt-renderer.md "Settings" is where a user reads the `render` keys: one row per
    field of RenderSettings, with the field's default."""
    import dataclasses

    from depthgt.settings import RenderSettings

    text = (REPO / "docs" / "gt-renderer.md").read_text().split("## Settings", 1)[1]
    rows = dict(re.findall(r"^\| `(\w+)` \| ([^|]+?) \|", text, re.M))
    fields = {f.name: f.default for f in dataclasses.fields(RenderSettings)}
    assert sorted(rows) == sorted(fields)
    for name, default in fields.items():
        written = rows[name].strip("`")
        if default is None or isinstance(default, bool | str):
            assert written == {None: "null", True: "true", False: "false"}.get(default, default), name
        else:
            assert float(written) == default, name

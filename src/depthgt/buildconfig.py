"""The config a build directory runs with, remembered between commands.

A working directory's config comes in layers, each merged over the one before as
Snakemake merges config files (mappings key by key, anything else replaced whole):

1. the **base**: the working directory's ``config/config.yaml`` when it has one, else the
   embedded default beside the Snakefile; a relative ``root:`` there is relative to the
   working directory;
2. the **remembered overrides** (:data:`OVERRIDES`, ``results/config/overrides.yaml``):
   every ``--configfile`` (and ``--config``) the build ran with so far, merged;
3. this command's ``--configfile`` files (and ``--config`` values); a relative ``root:``
   in such a file is relative to that file's folder (made absolute here, so the
   remembered overrides hold absolute roots).

The first real run in a directory writes the merged config it ran with
(:data:`REMEMBERED`, ``results/config/config.yaml``) and the overrides; every later
command there (``depthgt build``, ``rebuild``, ``report``, or ``python3 -m snakemake``)
runs with them without ``--configfile``. A command whose ``--configfile`` would change
keys of a directory that already has a build is refused, naming each key with the
value built and the value asked for, unless it is run with ``--reconfigure`` (or
:data:`RECONFIGURE_ENV` ``=1`` for a plain Snakemake run): then the change is
remembered and Snakemake's params rerun trigger rebuilds what the changed keys decide.
An edit of the base file itself is applied and announced (:func:`Layers.notice`).
``depthgt report`` shows the build as it was made: it refuses such a ``--configfile``
too, and tells to apply it with ``depthgt build --reconfigure`` first.

A ``--configfile`` with top-level keys that are no config keys is refused, naming the
file and the keys; when most of its keys are such, it is most likely a target (a JSON
output of the build) that Snakemake read as a config file, since its ``--configfile``
takes every value up to the next option, and the message says so.

Standard library and PyYAML only: the Snakefile imports it while it parses.
"""

from __future__ import annotations

import copy
import errno
import json
import math
import os
import shlex
import shutil
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from depthgt.atomic import write_atomic
from depthgt.errors import ConfigError, DepthGTError

__all__ = [
    "REMEMBERED",
    "OVERRIDES",
    "RECONFIGURE_ENV",
    "Layers",
    "merge",
    "changed_keys",
    "load_config_file",
    "base_config_file",
    "layered_config",
    "remember",
]

#: the merged config the last run in the working directory ran with (relative to it)
REMEMBERED = Path("results/config/config.yaml")
#: the --configfile layer of the build: every --configfile and --config value it ran with, merged
OVERRIDES = Path("results/config/overrides.yaml")
#: set to 1 to apply a --configfile that changes keys of an existing build (``depthgt build --reconfigure``)
RECONFIGURE_ENV = "DEPTHGT_RECONFIGURE"

_HEADER = {
    REMEMBERED: "# depthgt: the merged config the last run in this working directory ran with (written by it;\n"
    "# the next run names the keys that changed since). Reproduce it elsewhere with --configfile THIS_FILE.\n",
    OVERRIDES: "# depthgt: every --configfile (and --config) this build ran with, merged; applied over the\n"
    "# working directory's config/config.yaml (or the embedded default) by every later command here.\n",
}


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` merged over a copy of ``base`` as Snakemake merges config files:
    mappings key by key, any other value (lists included) replaced whole.

    >>> merge({"a": {"x": 1, "y": 2}, "s": [1, 2]}, {"a": {"y": 3}, "s": [9]})
    {'a': {'x': 1, 'y': 3}, 's': [9]}
    """
    out = copy.deepcopy(dict(base))
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value) if not isinstance(value, Mapping) else merge({}, value)
    return out


def _label(value: Any) -> str:
    """A config value in one line, as a person reads it in a message."""
    if isinstance(value, list) and value and all(isinstance(v, Mapping) and "name" in v for v in value):
        return "[" + ", ".join(str(v["name"]) for v in value) + "]"
    text = json.dumps(value, sort_keys=True, default=str)
    return text if len(text) <= 80 else text[:77] + "..."


def changed_keys(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Every key whose value differs between two configs, dotted, with both values
    (``key: old -> new``; ``(unset)`` for a key one of them lacks); ``sources`` entries
    are compared by name (``sources[kitchen]``).

    >>> changed_keys({"seed": 1, "frameset": {"stride": 2}}, {"seed": 1, "frameset": {"stride": 3}, "resize": 64})
    ['frameset.stride: 2 -> 3', 'resize: (unset) -> 64']
    """
    out = []
    for key in sorted(set(old) | set(new), key=str):
        a, b = old.get(key, _UNSET), new.get(key, _UNSET)
        name = f"{prefix}{key}"
        if a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)):
            continue
        if isinstance(a, Mapping) or isinstance(b, Mapping):
            if (isinstance(a, Mapping) or a is _UNSET) and (isinstance(b, Mapping) or b is _UNSET):
                out += changed_keys({} if a is _UNSET else a, {} if b is _UNSET else b, f"{name}.")
                continue
            out.append(
                f"{name}: {'(unset)' if a is _UNSET else _label(a)} -> {'(unset)' if b is _UNSET else _label(b)}"
            )
        elif name == "sources" and _named(a) and _named(b):
            olds, news = {s["name"]: s for s in a}, {s["name"]: s for s in b}
            for n in sorted(set(olds) | set(news)):
                if olds.get(n) != news.get(n):
                    before = "(unset)" if n not in olds else json.dumps(olds[n], sort_keys=True, default=str)
                    after = "(unset)" if n not in news else json.dumps(news[n], sort_keys=True, default=str)
                    out.append(f"sources[{n}]: {before} -> {after}")
            if [s["name"] for s in a] != [s["name"] for s in b] and set(olds) == set(news):
                out.append(f"sources: order {_label(a)} -> {_label(b)}")
        else:
            out.append(
                f"{name}: {'(unset)' if a is _UNSET else _label(a)} -> {'(unset)' if b is _UNSET else _label(b)}"
            )
    return out


_UNSET = object()


def _named(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(v, Mapping) and "name" in v for v in value)


def load_config_file(path: str | Path, what: str = "config file") -> dict[str, Any]:
    """A config file as Snakemake reads it (JSON first, then YAML; UTF-8), which must
    hold a mapping; an empty file is an empty mapping.

    Raises:
        ConfigError: a missing file, text that is not valid YAML (named with its line
            and column) or a document that is not a mapping, naming ``path``.
    """
    path = Path(path).absolute()
    if not path.is_file():
        raise ConfigError(f"{what} {path}: file not found")
    try:
        text = path.read_text(encoding="utf-8")
        try:
            doc = json.loads(text)
        except json.JSONDecodeError:
            doc = yaml.load(text, Loader=yaml.FullLoader)
    except (UnicodeDecodeError, yaml.YAMLError) as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        problem = getattr(err, "problem", None) or str(err)
        raise ConfigError(f"{what} {where}: not valid YAML ({problem})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{what} {path}: must hold a mapping of config keys, got {type(doc).__name__}")
    return doc


def base_config_file(workdir: str | Path, default: str | Path) -> Path:
    """The base layer: ``<workdir>/config/config.yaml`` when it exists, else ``default``
    (the embedded config beside the Snakefile)."""
    own = Path(workdir).absolute() / "config" / "config.yaml"
    return own if own.is_file() else Path(default).absolute()


def _with_absolute_roots(doc: dict[str, Any], folder: Path) -> tuple[dict[str, Any], dict[str, str]]:
    """``doc`` with each relative ``sources[].root`` made absolute against ``folder``;
    and source name -> the rule, for messages."""
    doc = copy.deepcopy(doc)
    rules = {}
    for src in doc.get("sources") or []:
        if isinstance(src, dict) and isinstance(src.get("root"), str):
            root = Path(src["root"]).expanduser()
            if not root.is_absolute():
                rules[str(src.get("name"))] = (
                    f"{src['root']} relative to the folder of the config file that sets it, {folder}"
                )
                src["root"] = os.path.normpath(folder / root)
    return doc, rules


@dataclass
class Layers:
    """The config a command in a working directory runs with (:func:`layered_config`).

    Attributes:
        config: the merged config (base, remembered overrides, this command's layer).
        overrides: the remembered overrides with this command's layer merged over them
            (what :func:`remember` writes).
        changes: the keys this command's layer changes in an existing build (empty for a
            directory without one), as :func:`changed_keys` writes them.
        base_changes: the keys that changed since the last run's config
            (:data:`REMEMBERED`) other than by this command's layer (an edited
            ``config/config.yaml``, a new default).
        base: the base file.
        root_rules: source name -> how its root was resolved (for messages).
        configfiles: this command's ``--configfile`` files, absolute, in order.
    """

    config: dict[str, Any]
    overrides: dict[str, Any]
    changes: list[str] = field(default_factory=list)
    base_changes: list[str] = field(default_factory=list)
    base: Path | None = None
    root_rules: dict[str, str] = field(default_factory=dict)
    configfiles: list[Path] = field(default_factory=list)

    def refusal(self, workdir: str | Path, command: str = "build") -> str:
        """The message that refuses this command's changes (``changes``); what to do
        instead depends on the ``command``: ``build`` (``depthgt build`` or ``rebuild``,
        a plain Snakemake run) or ``report`` (``depthgt report``, which has no
        ``--reconfigure``: it shows the build as it was made)."""
        wd = Path(workdir).absolute()
        head = (
            f"--configfile would change the config the build in {wd} was made with ({self.base} with "
            f"{wd / OVERRIDES}): " + "; ".join(self.changes)
        )
        if command == "report":
            files = " ".join(f"--configfile {shlex.quote(str(c))}" for c in self.configfiles)
            return (
                f"{head}. depthgt report shows the build as it was made and takes no --reconfigure: leave "
                f"--configfile out to report on the build, or apply the change to the build first "
                f"(depthgt build -d {shlex.quote(str(wd))} --reconfigure {files}; the outputs these keys decide "
                "are built again), then run depthgt report without --configfile"
            )
        return (
            f"{head}. Leave --configfile out to go on with the build's config, pass --reconfigure to apply the "
            f"change (the outputs these keys decide are built again; plain snakemake: {RECONFIGURE_ENV}=1), "
            "or use another working directory (-d)"
        )

    def notice(self) -> str | None:
        """A line announcing ``base_changes`` (None when there are none)."""
        if not self.base_changes:
            return None
        return (
            f"depthgt: the config changed since the last run in this working directory ({self.base}): "
            + "; ".join(self.base_changes)
            + ". The outputs these keys decide are built again."
        )


def layered_config(
    workdir: str | Path,
    default: str | Path,
    configfiles: Sequence[str | Path] = (),
    config_args: Mapping[str, Any] | None = None,
    reconfigure: bool | None = None,
    check_sources: bool = True,
    config_keys: Collection[str] | None = None,
    command: str = "build",
) -> Layers:
    """The config of a command in ``workdir`` (module docstring).

    Args:
        default: the embedded default config (the base when ``workdir`` has no
            ``config/config.yaml``).
        configfiles: this command's ``--configfile`` files, in order.
        config_args: this command's ``--config`` values (merged last).
        reconfigure: apply changes to an existing build; None: read :data:`RECONFIGURE_ENV`.
        check_sources: check that every source's root exists (:func:`check_roots`;
            ``depthgt report`` reads the results only).
        config_keys: the top-level config keys (:data:`depthgt.settings.TOP_LEVEL_KEYS`):
            a ``--configfile`` with other top-level keys is refused (:func:`unknown_keys`);
            None: not checked.
        command: what runs, for the refusal's advice (:meth:`Layers.refusal`).

    Raises:
        ConfigError: a file that does not parse; a ``--configfile`` with unknown keys; a
            ``root`` that does not exist (naming the resolved path and the rule); changes
            to an existing build without ``reconfigure`` (:meth:`Layers.refusal`).
    """
    wd = Path(workdir).absolute()
    if reconfigure is None:
        reconfigure = os.environ.get(RECONFIGURE_ENV, "") not in ("", "0")
    base_file = base_config_file(wd, default)
    base = load_config_file(base_file)
    rules = {
        str(s.get("name")): f"{s['root']} relative to the working directory {wd}"
        for s in base.get("sources") or []
        if isinstance(s, dict) and isinstance(s.get("root"), str) and not Path(s["root"]).expanduser().is_absolute()
    }
    stored = load_config_file(wd / OVERRIDES, "remembered config") if (wd / OVERRIDES).is_file() else None
    layer: dict[str, Any] = {}  # this command's --configfile files and --config values
    for path in configfiles:
        loaded = load_config_file(path, "--configfile")
        if config_keys is not None and set(map(str, loaded)) - set(config_keys):
            raise ConfigError(unknown_keys(path, loaded, config_keys))
        doc, file_rules = _with_absolute_roots(loaded, Path(path).absolute().parent)
        if "sources" in doc:
            rules = dict(file_rules)
        layer = merge(layer, doc)
    if config_args:
        layer = merge(layer, dict(config_args))
    built_with = merge(base, stored or {})
    new = merge(built_with, layer)
    layers = Layers(
        config=new,
        overrides=merge(stored or {}, layer),
        base=base_file,
        root_rules=rules,
        configfiles=[Path(p).absolute() for p in configfiles],
    )
    if (wd / REMEMBERED).is_file():
        layers.changes = changed_keys(built_with, new)
        last = load_config_file(wd / REMEMBERED, "remembered config")
        layers.base_changes = changed_keys(last, built_with)
        if layers.changes and not reconfigure:
            raise ConfigError(layers.refusal(wd, command))
    if check_sources:
        check_roots(new, wd, rules)
    return layers


def unknown_keys(path: str | Path, doc: Mapping[str, Any], config_keys: Collection[str]) -> str:
    """The message refusing a ``--configfile`` with top-level keys that are no config
    keys, naming them. When they are most of its keys, the file is most likely a target
    written after ``--configfile`` (``snakemake --configfile mine.yaml
    results/scenes/syn/r0/index.json``) that Snakemake read as a second config file: the
    message says where targets go.

    >>> print(unknown_keys("/wd/results/scenes/syn/r0/index.json", {"dataset": "syn", "frames": 1, "poses": 2},
    ...     ["dataset", "seed"]))
    --configfile /wd/results/scenes/syn/r0/index.json: unknown config key(s) frames, poses (allowed: dataset, seed). Is it a target? Snakemake reads every value after --configfile, up to the next option, as a config file: write targets before --configfile (snakemake TARGET ... --configfile FILE)
    >>> print(unknown_keys("/mine.yaml", {"seed": 1, "sed": 2}, ["seed"]))
    --configfile /mine.yaml: unknown config key(s) sed (allowed: seed)
    """
    unknown = [str(k) for k in doc if str(k) not in config_keys]
    shown = ", ".join(unknown[:8]) + (f", ... ({len(unknown)} keys)" if len(unknown) > 8 else "")
    message = (
        f"--configfile {Path(path).absolute()}: unknown config key(s) {shown} "
        f"(allowed: {', '.join(sorted(config_keys))})"
    )
    if 2 * len(unknown) > len(doc):
        message += (
            ". Is it a target? Snakemake reads every value after --configfile, up to the next option, as a config "
            "file: write targets before --configfile (snakemake TARGET ... --configfile FILE)"
        )
    return message


def check_roots(config: Mapping[str, Any], workdir: str | Path, rules: Mapping[str, str] | None = None) -> None:
    """Every source's ``root`` exists; a missing one is named with its absolute path and
    how it was resolved (relative to the working directory, or to its config file).

    Raises:
        ConfigError: ``sources[NAME].root: /abs/path does not exist (...)``.
    """
    wd = Path(workdir).absolute()
    for src in config.get("sources") or []:
        if not isinstance(src, Mapping) or not isinstance(src.get("root"), str):
            continue
        name = str(src.get("name"))
        path = Path(src["root"]).expanduser()
        where = path if path.is_absolute() else wd / path
        if not where.exists():
            rule = (rules or {}).get(name)
            if rule is None and not path.is_absolute():
                rule = f"{src['root']} relative to the working directory {wd}"
            raise ConfigError(
                f"config key sources[{name}].root: {os.path.normpath(where)} does not exist"
                + (f" ({rule})" if rule else "")
            )


def remember(workdir: str | Path, layers: Layers) -> list[Path]:
    """Write the merged config and the overrides of a run into ``workdir`` (atomically,
    :func:`depthgt.atomic.write_atomic`; unchanged files are not rewritten). Returns the
    files written.

    Raises:
        DepthGTError: a file that cannot be written (a full disk, no permission), in one
            line naming it, why and the space free there; no temporary file is left.
    """
    wd = Path(workdir).absolute()
    written = []
    for rel, doc in ((OVERRIDES, layers.overrides), (REMEMBERED, layers.config)):
        path = wd / rel
        text = _HEADER[rel] + yaml.safe_dump(json.loads(json.dumps(doc, default=str)), sort_keys=False)
        try:
            if path.is_file() and path.read_text(encoding="utf-8") == text:
                continue
            write_atomic(path, _write_text, text)
        except OSError as err:
            raise DepthGTError(_unwritable(path, err)) from None
        written.append(path)
    return written


def _write_text(path: Path, text: str) -> None:
    path.write_text(text, encoding="utf-8")


def _unwritable(path: Path, err: OSError) -> str:
    """The line refusing a run whose config cannot be remembered in ``path``."""
    reason = err.strerror or str(err)
    if err.filename and Path(err.filename).name not in (path.name, f".{path.name}.tmp{path.suffix}"):
        reason += f": {err.filename}"  # a folder on the way (a file where results/config should be)
    where = path.parent
    while not where.is_dir() and where != where.parent:
        where = where.parent
    try:
        free = f"{shutil.disk_usage(where).free / 1e6:.1f} MB free on its file system"
    except OSError:
        free = "free space unknown"
    advice = "free space and run again" if err.errno in (errno.ENOSPC, errno.EDQUOT) else "fix that and run again"
    return f"cannot remember the run's config in {path}: {reason} ({free}); {advice}"

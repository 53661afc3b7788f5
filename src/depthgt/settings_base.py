"""What every stage's settings are made of (standard library only).

A stage's settings are one frozen dataclass (or a few) in the ``settings`` module beside
the stage (``gt/render/settings.py``, ``registration/settings.py``, ...), declared with
:func:`section`: its fields are the keys of one config section and their defaults the
config's defaults, and a field whose values are a fixed set says so in its type
(``plane: Literal["fit", "normals", "none"] = "fit"``): the one place the set is written.
:func:`build` makes the class from a config mapping and is the one check of a config's
keys and types: unknown keys (:func:`check_keys`), missing required keys, types and
choices, every error naming the key (``config key render.plane: ...``); the class's own
``__post_init__`` checks the rest (bounds, consistency between fields) with
:func:`require`. :mod:`depthgt.settings` builds every section with it.

>>> @section("demo")
... class Demo:
...     mode: Literal["a", "b"] = "a"
...     size: int = 4
>>> build(Demo, {"size": 8}, "demo")
Demo(mode='a', size=8)
>>> Demo(mode="c")
Traceback (most recent call last):
...
depthgt.errors.ConfigError: config key demo.mode: must be one of a, b, got 'c'
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, Literal, NoReturn, TypeVar, dataclass_transform

from depthgt.errors import ConfigError

__all__ = ["fail", "require", "section", "check_keys", "build", "mapping", "choices"]

T = TypeVar("T")


def fail(key: str, message: str) -> NoReturn:
    """Raise :class:`ConfigError` naming the config key ``key``."""
    raise ConfigError(f"config key {key}: {message}")


def require(ok: bool, key: str, message: str) -> None:
    """:func:`fail` unless ``ok``."""
    if not ok:
        fail(key, message)


@dataclass_transform(frozen_default=True)
def section(where: str) -> Callable[[type[T]], type[T]]:
    """Make a class the settings of the config section ``where`` (``"render"``; a
    ``{field}`` in it is the instance's value, ``"sources[{name}]"``): a frozen
    dataclass whose ``Literal`` fields are checked, naming ``where.field``, before its
    own ``__post_init__`` runs (also when it is made in code, not from a config)."""

    def wrap(cls: type[T]) -> type[T]:
        own = cls.__dict__.get("__post_init__")

        def __post_init__(self) -> None:
            _check_choices(self, where.format_map(vars(self)) if "{" in where else where)
            if own is not None:
                own(self)

        cls.__post_init__ = __post_init__
        return dataclasses.dataclass(frozen=True)(cls)

    return wrap


def check_keys(section: Mapping[str, Any], allowed, where: str) -> None:
    """Raise :class:`ConfigError` naming every key of ``section`` not in ``allowed``.

    The one unknown-key check of the project (every settings class goes through it).
    """
    unknown = sorted(set(section) - set(allowed), key=str)
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + str(k) for k in unknown)}; "
            f"allowed{' in ' + where if where else ''}: {', '.join(sorted(map(str, allowed)))}"
        )


def build(cls: type[T], section: Mapping[str, Any] | T | None, where: str) -> T:
    """``cls`` from a config mapping: unknown keys rejected, required keys asked for,
    nested settings built, lists turned into tuples where the field is a tuple, scalar
    types and choices checked; every error names ``where.key``."""
    if section is None:
        section = {}
    if isinstance(section, cls):
        return section
    if not isinstance(section, Mapping):
        fail(where, f"must be a mapping, got {type(section).__name__} {section!r}")
    hints = _hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.init]
    check_keys(section, [f.name for f in fields], where)
    for f in fields:
        if f.name not in section and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            fail(_key(where, f.name), "required (it has no default)")
    values = {k: _coerce(hints[k], v, _key(where, k)) for k, v in section.items()}
    try:
        return cls(**values)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(f"config key {where}: {err}") from err


def mapping(value, where: str) -> dict:
    """A section that holds other sections (``enhance``) as a dict: None is empty,
    anything but a mapping :func:`fail`."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        fail(where, f"must be a mapping, got {type(value).__name__} {value!r}")
    return dict(value)


def choices(hint) -> tuple:
    """The values a ``Literal`` type hint (or a union holding one) allows; () for none.

    >>> choices(Literal["a", "b"] | None)
    ('a', 'b')
    """
    return tuple(a for o in _options(hint) if typing.get_origin(o) is Literal for a in typing.get_args(o))


def _key(where: str, name: str) -> str:
    """The dotted config key of ``name`` in the section ``where`` ("" is the top level)."""
    return f"{where}.{name}" if where else name


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _options(hint) -> tuple:
    """The alternatives of a type hint (``int | None`` -> (int, NoneType))."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return typing.get_args(hint)
    return (hint,)


def _yaml(value) -> str:
    """A value as the config writes it (``true``, ``fit``)."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def _choice_problem(hint, value) -> str | None:
    """Why ``value`` is none of the choices of a field with a ``Literal`` hint, or None."""
    allowed = choices(hint)
    options = _options(hint)
    if any(type(value) is type(a) and value == a for a in allowed) or any(
        _is(value, o) for o in options if o in (bool, int, float, str)
    ):
        return None
    if value is None and type(None) in options:
        return None
    named = [*map(_yaml, allowed), *(("true", "false") if bool in options else ())]
    return f"must be one of {', '.join(named)}{' or null' if type(None) in options else ''}, got {value!r}"


def _check_choices(obj, where: str) -> None:
    for name, hint in _hints(type(obj)).items():
        if choices(hint) and (problem := _choice_problem(hint, getattr(obj, name))):
            fail(_key(where, name), problem)


def _coerce(hint, value, where: str):
    options = _options(hint)
    if value is None:
        if type(None) in options:
            return None
        fail(where, "must not be null")
    for opt in options:
        if dataclasses.is_dataclass(opt) and isinstance(value, Mapping):
            return build(opt, value, where)
        if typing.get_origin(opt) is tuple and isinstance(value, (list, tuple)):
            return _tuple_of(opt, value, where)
    if choices(hint):
        if problem := _choice_problem(hint, value):
            fail(where, problem)
        return value
    scalars = [o for o in options if o in (int, float, bool, str)]
    structured = [o for o in options if dataclasses.is_dataclass(o) or typing.get_origin(o) is tuple]
    if structured and not scalars and not any(isinstance(value, o) for o in options if isinstance(o, type)):
        kinds = " or ".join("a mapping" if dataclasses.is_dataclass(o) else "a list" for o in structured)
        fail(where, f"must be {kinds}, got {type(value).__name__} {value!r}")
    if scalars and not any(_is(value, o) for o in scalars):
        fail(where, _wrong_type(scalars, value))
    if float in scalars and not isinstance(value, float) and _is(value, float) and int not in scalars:
        return float(value)
    return value


def _tuple_of(hint, value, where: str) -> tuple:
    """``value`` as a tuple, its items checked where the hint gives them one scalar type
    (``tuple[int, ...]``); nested settings and other item types are left to their checks."""
    args = [a for a in typing.get_args(hint) if a is not Ellipsis]
    if len(set(args)) == 1 and args[0] in (int, float, bool, str):
        for i, item in enumerate(value):
            if not _is(item, args[0]):
                fail(f"{where}[{i}]", _wrong_type([args[0]], item))
    return tuple(value)


def _wrong_type(kinds, value) -> str:
    """The message for ``value`` of none of ``kinds``; for a number that YAML read as text
    (YAML 1.1 takes ``1e-4``, without a dot, for a string) it says how to write it."""
    msg = f"must be {' or '.join(k.__name__ for k in kinds)}, got {type(value).__name__} {value!r}"
    if float in kinds and isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return msg
        if math.isfinite(number):
            msg += f" (YAML reads a number such as 1e-4 without a dot as text: write {number!r})"
    return msg


def _is(value, kind) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, kind)

"""Factories from the validated config (a plain dict) to per-stage settings.

Components never see the config object: the workflow passes plain dicts of one
section, and these factories turn them into frozen dataclasses, raising
:class:`~depthgt.errors.ConfigError` that names the key at fault.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

from depthgt.errors import ConfigError

T = TypeVar("T")


def build(cls: type[T], section: dict[str, Any] | None, where: str) -> T:
    """``cls(**section)`` with errors that name ``where.key``.

    >>> from depthgt.gt.patches import PatchSettings
    >>> build(PatchSettings, {"count": 3}, "patches").count
    3
    """
    section = dict(section or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(section) - names)
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(f'{where}.{k}' for k in unknown)}; allowed: {', '.join(sorted(names))}")
    try:
        return cls(**section)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"invalid {where}: {err}") from err


def job_settings(config: dict[str, Any]):
    """The :class:`~depthgt.gt.frameset.JobSettings` of the per-frame-set job."""
    from depthgt.gt.framesets import FrameSetSettings
    from depthgt.gt.patches import PatchSettings
    from depthgt.gt.frameset import JobSettings
    from depthgt.gt.render import GTRenderSettings

    reg = dict(config.get("registration") or {})
    method = reg.pop("method", "given")
    on_failure = reg.pop("on_failure", "drop_neighbours")
    size = int(config.get("resize", 256))
    return JobSettings(
        size_hw=(size, size),
        frameset=build(FrameSetSettings, config.get("frameset"), "frameset"),
        patches=build(PatchSettings, config.get("patches"), "patches"),
        render=build(GTRenderSettings, config.get("render"), "render"),
        registration_method=method,
        registration=reg,
        registration_on_failure=on_failure,
        seed=int(config.get("seed", 0)),
        device=str(config.get("device", "auto")),
    )


def check_config(config: dict[str, Any], schema_path: str) -> None:
    """Validate ``config`` against the JSON schema and raise one :class:`ConfigError`
    listing every problem as ``key.path: message`` (Snakemake's own validation, run
    afterwards to fill defaults, reports only the first error with the whole schema)."""
    import jsonschema
    import yaml

    with open(schema_path) as fh:
        schema = yaml.safe_load(fh)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: list(map(str, e.absolute_path)))
    if errors:
        lines = []
        for err in errors:
            path = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err.absolute_path).lstrip(".") or "(top level)"
            lines.append(f"  config key {path}: {err.message}")
        raise ConfigError("invalid configuration:\n" + "\n".join(lines))

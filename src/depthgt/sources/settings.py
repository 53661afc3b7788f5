"""The settings of one RGB-D source (an entry of config ``sources``), checked without
opening any data (numpy only: :mod:`depthgt.settings` builds them when the workflow
starts). A source's ``kind`` is any kind of :data:`depthgt.sources.base.KINDS`, those
registered from outside depthgt (:func:`depthgt.sources.base.register`) included."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import field
from typing import Literal

from depthgt.gt.settings import Split
from depthgt.settings_base import fail, require, section
from depthgt.sources.base import check_options, known_kinds

__all__ = ["SourceSettings", "check_scene_name"]

_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def check_scene_name(scene: str, where: str) -> None:
    """A scene name must be usable as one path component."""
    if not isinstance(scene, str) or scene in ("", ".", "..") or "/" in scene:
        fail(where, f"scene name {scene!r} cannot be a path component; name the sequence folder (or use scenes: all)")


@section("sources[{name}]")
class SourceSettings:
    """One entry of config ``sources``: an RGB-D source of the adapter ``kind``.

    ``colour_matches_depth``: ``auto`` (the kind's, :data:`depthgt.sources.base.KINDS`:
    synthetic only), ``true`` or ``false``: whether the source's colour is taken by the
    depth's camera at the depth's instant, which decides ``registration.photometric:
    auto`` (e.g. ``true`` for synthetic or pre-registered data in ScanNet's layout).
    """

    name: str
    kind: str
    root: str | None = None
    scenes: str | tuple[str, ...] = "all"
    split: Literal["auto", Split] = "auto"
    options: dict = field(default_factory=dict)
    colour_matches_depth: bool | Literal["auto"] = "auto"

    def __post_init__(self):
        where = f"sources[{self.name}]"
        require(bool(_NAME.match(self.name)), f"{where}.name", "must match [A-Za-z0-9_.-]+ (it names output folders)")
        require(
            self.kind in known_kinds(),
            f"{where}.kind",
            f"unknown kind {self.kind!r}; known: {', '.join(known_kinds())}",
        )
        if self.scenes != "all":
            require(
                isinstance(self.scenes, tuple) and len(self.scenes) >= 1,
                f"{where}.scenes",
                "must be 'all' or a non-empty list of scene names",
            )
            for scene in self.scenes:
                check_scene_name(scene, f"{where}.scenes")
        require(isinstance(self.options, Mapping), f"{where}.options", "must be a mapping")
        check_options(self.kind, self.options, f"config key {where}.options")

"""The one shape check of the library's inputs: an argument's shape against a spec string.

A spec names the dimensions as the docstrings write them: ``"B 1 H W"`` (commas and
parentheses are optional, ``"(B, 1, H, W)"`` is the same spec). Each token is

* a name (``B``, ``H``, ``n_frames``): any size, but the same name has the same size
  everywhere it appears, in this spec and in the ``sizes`` bound by earlier checks;
* an integer: exactly that size;
* ``*``: any one dimension; ``...``: any number of dimensions, none included (at most
  one per spec).

Alternatives are separated by ``|`` (``"H W | B 1 H W"``); the first that fits binds.
:func:`check_shape` returns the sizes its names bound, added to those it was given, so
that checks of several arguments chain::

    sizes = check_shape(points_cam, "B N 3", "points_cam")
    check_shape(K, "B 3 3", "K", sizes)   # K's B must be points_cam's

The error names the argument, the spec with the sizes already bound (``B=2``) and the
shape it got, e.g. ``K must be (B=2, 3, 3), got (3, 3)``. Anything with a ``.shape``
is checked (numpy arrays, torch tensors); the module imports neither.

Intrinsics follow one convention (docs/development.md "Shapes and intrinsics"): a
function taking the intrinsics of a batch of images takes ``K`` (B, 3, 3), one per
image; a function taking a frame set's images, which share one camera, takes the frame
set's ``K`` (3, 3) and says so.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache

__all__ = ["check_shape"]

_ANY = "*"
_REST = "..."


@lru_cache(maxsize=256)
def _parse(spec: str) -> tuple[tuple[str | int, ...], ...]:
    """The alternatives of ``spec``, each a tuple of tokens (names, ints, ``*``, ``...``)."""
    alternatives = []
    for part in spec.split("|"):
        text = part.strip()
        if text.startswith("(") and text.endswith(")"):
            text = text[1:-1]
        tokens: list[str | int] = []
        for raw in text.replace(",", " ").split():
            if raw.isdigit():
                tokens.append(int(raw))
            elif raw in (_ANY, _REST) or raw.isidentifier():
                tokens.append(raw)
            else:
                raise ValueError(f"shape spec {spec!r}: {raw!r} is not a name, an integer, '*' or '...'")
        if tokens.count(_REST) > 1:
            raise ValueError(f"shape spec {spec!r}: '...' may appear once per alternative")
        alternatives.append(tuple(tokens))
    return tuple(alternatives)


def _bind(tokens: tuple[str | int, ...], shape: tuple[int, ...], sizes: Mapping[str, int]) -> dict[str, int] | None:
    """The names of ``tokens`` bound by ``shape`` (None where ``shape`` does not fit)."""
    if _REST in tokens:
        i = tokens.index(_REST)
        head, tail = tokens[:i], tokens[i + 1 :]
        if len(shape) < len(head) + len(tail):
            return None
        pairs = list(zip(head, shape[: len(head)])) + list(zip(tail, shape[len(shape) - len(tail) :]))
    else:
        if len(shape) != len(tokens):
            return None
        pairs = list(zip(tokens, shape))
    bound: dict[str, int] = {}
    for token, size in pairs:
        if token == _ANY:
            continue
        if isinstance(token, int):
            if size != token:
                return None
            continue
        want = bound.get(token, sizes.get(token))
        if want is not None and size != want:
            return None
        bound[token] = size
    return bound


def _render(tokens: tuple[str | int, ...], sizes: Mapping[str, int]) -> str:
    words = [f"{t}={sizes[t]}" if isinstance(t, str) and t in sizes else str(t) for t in tokens]
    return f"({words[0]},)" if len(words) == 1 else f"({', '.join(words)})"


def check_shape(x, spec: str, name: str, sizes: Mapping[str, int] | None = None) -> dict[str, int]:
    """The sizes the names of ``spec`` take in ``x.shape``; a ValueError if it does not fit.

    Args:
        x: anything with a ``.shape`` (a numpy array, a torch tensor).
        spec: the expected shape, e.g. ``"B 1 H W"`` (module docstring).
        name: the argument as the error names it (``"depth_m"``, ``"frame 3: K"``).
        sizes: sizes of names bound before (what an earlier call returned); not modified.

    Returns:
        ``sizes`` with the names of ``spec`` added, each with its size in ``x``.

    Raises:
        ValueError: naming ``name``, the spec with the sizes bound before and ``x``'s shape.
        TypeError: ``x`` has no ``.shape``.

    >>> import numpy as np
    >>> sizes = check_shape(np.zeros((2, 5, 3)), "B N 3", "points_cam")
    >>> sizes
    {'B': 2, 'N': 5}
    >>> check_shape(np.zeros((2, 3, 3)), "B 3 3", "K", sizes)
    {'B': 2, 'N': 5}
    >>> check_shape(np.zeros((3, 3)), "B 3 3", "K", sizes)
    Traceback (most recent call last):
    ...
    ValueError: K must be (B=2, 3, 3), got (3, 3)
    >>> check_shape(np.zeros((4, 4, 4)), "... 4 4", "T")
    {}
    >>> check_shape(np.zeros((2, 3, 8, 8)), "H W | B 1 H W", "depth")
    Traceback (most recent call last):
    ...
    ValueError: depth must be (H, W) or (B, 1, H, W), got (2, 3, 8, 8)
    """
    sizes = dict(sizes or {})
    if not hasattr(x, "shape"):
        raise TypeError(f"{name} must be an array or tensor of shape {spec}, got {type(x).__name__}")
    shape = tuple(int(d) for d in x.shape)
    alternatives = _parse(spec)
    for tokens in alternatives:
        bound = _bind(tokens, shape, sizes)
        if bound is not None:
            sizes.update(bound)
            return sizes
    expected = " or ".join(_render(tokens, sizes) for tokens in alternatives)
    raise ValueError(f"{name} must be {expected}, got {shape}")

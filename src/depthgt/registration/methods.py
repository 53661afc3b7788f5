"""The registration methods by their ``registration.method`` name: one entry each, every
one a :class:`~depthgt.registration.frameset.Registration`."""

from __future__ import annotations

from depthgt.registration.frameset import Registration
from depthgt.registration.given import register_given
from depthgt.registration.local import register_refine
from depthgt.registration.overfit import register_overfit

__all__ = ["METHODS"]

#: The registration methods by their ``registration.method`` name
#: (:data:`depthgt.settings.REGISTRATION_METHODS`, the same names, is what the config checks).
METHODS: dict[str, Registration] = {
    "given": register_given,
    "refine": register_refine,
    "overfit": register_overfit,
}

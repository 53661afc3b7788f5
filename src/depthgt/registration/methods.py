"""The registration methods by their ``registration.method`` name: one entry each, every
one a :class:`~depthgt.registration.frameset.Registration`."""

from __future__ import annotations

from depthgt.registration.frameset import Registration
from depthgt.registration.given import register_given
from depthgt.registration.local import refine_source_poses_many, register_refine
from depthgt.registration.overfit import register_overfit

__all__ = ["METHODS", "TOGETHER"]

#: The registration methods by their ``registration.method`` name
#: (:data:`depthgt.settings.REGISTRATION_METHODS`, the same names, is what the config checks).
METHODS: dict[str, Registration] = {
    "given": register_given,
    "refine": register_refine,
    "overfit": register_overfit,
}

#: The methods that register several frame sets of one camera together (on a GPU), by
#: name: ``(datas, offsets, settings) -> [RegistrationResult]``, one result per set as the
#: method's own gives it.
TOGETHER = {
    "refine": refine_source_poses_many,
}

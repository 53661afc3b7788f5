"""Registration of local frame sets: the neighbours' poses in the target camera.

Every method is a :class:`~depthgt.registration.frameset.Registration`, a function
``(data, offsets, settings, *, seed, encoder_state) -> RegistrationResult`` in its own
module, one entry of :data:`METHODS` (:mod:`depthgt.registration.methods`, with what
each needs and costs) by its ``registration.method`` name: ``given``
(:func:`~depthgt.registration.given.register_given`, the source's poses), ``refine``
(:func:`~depthgt.registration.local.register_refine`, the source's poses refined on the
set) and ``overfit`` (:func:`~depthgt.registration.overfit.register_overfit`, the
paper's registration, Sec. 3.2). Their failure checks: :mod:`depthgt.registration.checks`;
the frame set's members read at the working size: :func:`load_frameset`; the method
run with the photometric rule, and which members enter the GT: :func:`align`.
Also :func:`pretrain_encoder` (stream-only pretraining) and :func:`build_encoder`.
Settings and presets: :mod:`depthgt.registration.settings` (torch-free, as is
:mod:`depthgt.registration.methods`): the names below are imported on first use
(:mod:`depthgt.lazy`), so that importing those two imports no torch.
"""

from typing import TYPE_CHECKING

from depthgt.lazy import lazy_names

if TYPE_CHECKING:  # the package's names, each imported on first use (below)
    from depthgt.registration.align import Alignment, align, align_many, photometric_for
    from depthgt.registration.encoder import build_encoder
    from depthgt.registration.frameset import (
        FrameSetData,
        Registration,
        load_depth,
        load_frameset,
        load_poses,
        poses_from_source,
    )
    from depthgt.registration.given import register_given
    from depthgt.registration.local import refine_source_poses, register_refine
    from depthgt.registration.methods import METHODS
    from depthgt.registration.overfit import pretrain_encoder, register_frameset, register_overfit
    from depthgt.registration.refine import refine_poses
    from depthgt.registration.result import RegistrationResult

__all__ = [
    "METHODS",
    "Alignment",
    "align",
    "align_many",
    "load_depth",
    "load_frameset",
    "load_poses",
    "photometric_for",
    "FrameSetData",
    "Registration",
    "RegistrationResult",
    "build_encoder",
    "poses_from_source",
    "pretrain_encoder",
    "refine_poses",
    "refine_source_poses",
    "register_frameset",
    "register_given",
    "register_overfit",
    "register_refine",
]

__getattr__, __dir__ = lazy_names(__name__, __file__)

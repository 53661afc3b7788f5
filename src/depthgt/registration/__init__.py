"""Overfit-trained unsupervised registration of local frame sets (paper Sec. 3.2).

Entry points: :func:`register_frameset` (one frame set -> :class:`RegistrationResult`),
:func:`refine_source_poses` (a source's poses refined on the frame set),
:func:`pretrain_encoder` (stream-only pretraining), :func:`build_encoder`. Settings and
presets: :class:`depthgt.settings.RegistrationSettings`,
:func:`depthgt.settings.registration_settings`. Imported lazily by callers (torch is heavy).
"""

from depthgt.registration.encoder import build_encoder
from depthgt.registration.local import refine_source_poses
from depthgt.registration.overfit import pretrain_encoder, register_frameset
from depthgt.registration.refine import refine_poses
from depthgt.registration.result import RegistrationResult

__all__ = [
    "RegistrationResult",
    "build_encoder",
    "pretrain_encoder",
    "refine_poses",
    "refine_source_poses",
    "register_frameset",
]

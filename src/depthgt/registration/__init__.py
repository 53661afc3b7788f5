"""Overfit-trained unsupervised registration of local frame sets (paper Sec. 3.2).

Entry points: :func:`register_frameset` (one frame set -> :class:`RegistrationResult`),
:func:`pretrain_encoder` (stream-only pretraining), :func:`build_encoder`,
:data:`PRESETS` / :func:`make_settings`. Imported lazily by callers (torch is heavy).
"""

from depthgt.registration.encoder import build_encoder
from depthgt.registration.metrics import pose_errors, rotation_error_deg, translation_error_cm
from depthgt.registration.overfit import (
    PRESETS,
    RegistrationResult,
    RegistrationSettings,
    make_settings,
    pretrain_encoder,
    register_frameset,
)
from depthgt.registration.refine import RefineSettings, refine_poses

__all__ = [
    "PRESETS", "RegistrationResult", "RegistrationSettings", "RefineSettings", "build_encoder", "make_settings",
    "pose_errors", "pretrain_encoder", "refine_poses", "register_frameset", "rotation_error_deg",
    "translation_error_cm",
]

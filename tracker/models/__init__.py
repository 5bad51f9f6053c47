"""Models the tracker's kernels share: motion (static, constant velocity) and S(n, k)."""

from tracker.models.motion import (
    MOTION_CV,
    MOTION_STATIC,
    ConstantVelocity,
    MotionModel,
    Static,
    cv_cov_entry,
    cv_mean_entry,
    cv_noise_entry,
    cv_predict,
)
from tracker.models.sfunc import KIND_EXP, KIND_POISSON, ExpS, PoissonS, SModel, log_s, log_s_ratio

__all__ = [
    "KIND_EXP",
    "KIND_POISSON",
    "MOTION_CV",
    "MOTION_STATIC",
    "ConstantVelocity",
    "ExpS",
    "MotionModel",
    "PoissonS",
    "SModel",
    "Static",
    "cv_cov_entry",
    "cv_mean_entry",
    "cv_noise_entry",
    "cv_predict",
    "log_s",
    "log_s_ratio",
]

"""The tracker's data types, as arrays: report batches, hypotheses (with their motion models) and the estimate."""

from tracker.types.estimate import Estimate
from tracker.types.hypotheses import ConstantVelocity, Hypotheses, MotionModel, Static
from tracker.types.reports import Reports, check_gaussians, gaussian_product

__all__ = [
    "ConstantVelocity",
    "Estimate",
    "Hypotheses",
    "MotionModel",
    "Reports",
    "Static",
    "check_gaussians",
    "gaussian_product",
]

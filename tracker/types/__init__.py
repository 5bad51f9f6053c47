"""The tracker's data types, as arrays: report batches (checked once, when built), hypotheses and the estimate."""

from tracker.types.estimate import Estimate
from tracker.types.hypotheses import Hypotheses
from tracker.types.reports import Reports, check_gaussians, gaussian_product

__all__ = ["Estimate", "Hypotheses", "Reports", "check_gaussians", "gaussian_product"]

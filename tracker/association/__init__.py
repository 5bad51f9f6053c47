"""Association: the greedy association-estimation tracker of paper 1 (Fig. 3) with its numba walk, and the
batch search and sampler over partitions under the same model (:mod:`tracker.association.batch`)."""

from tracker.association.batch import (
    BatchAssociator,
    BatchResult,
    associate_batch,
    batch_estimate,
    log_posterior,
)
from tracker.association.greedy import (
    BLOCK,
    DEFAULT_GAMMA,
    GATE_PROB,
    VARIANTS,
    AssociationResult,
    Tracker,
    associate,
    perfect_estimate,
)

__all__ = [
    "BLOCK",
    "DEFAULT_GAMMA",
    "GATE_PROB",
    "VARIANTS",
    "AssociationResult",
    "BatchAssociator",
    "BatchResult",
    "Tracker",
    "associate",
    "associate_batch",
    "batch_estimate",
    "log_posterior",
    "perfect_estimate",
]

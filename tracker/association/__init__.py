"""Association: the greedy association-estimation tracker of paper 1 (Fig. 3) and its numba walk."""

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
    "Tracker",
    "associate",
    "perfect_estimate",
]

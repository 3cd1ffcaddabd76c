"""Where the seed group's trust-region step used to live; it is now :mod:`sg_torchrl.objectives.stacked_trust_region`.

The step is written once, for S stacked seeds, in :mod:`sg_torchrl.objectives` (the single-seed
steps are its S = 1 case); these names stay importable from here for existing code.
"""

from sg_torchrl.objectives.second_order import (
    SeedFisherVectorProduct,
    SeedLinearisation,
    seed_conjugate_gradient,
    seed_flat_grad,
    seed_linearise,
)
from sg_torchrl.objectives.stacked_trust_region import (
    SeedProposals,
    SeedSurrogates,
    StackedCPOStep,
    StackedNaturalPolicyStep,
    StackedPCPOStep,
    StackedTRPOStep,
    StackedTrustRegionStep,
)
from sg_torchrl.objectives.trust_region import STACKED_STEPS

__all__ = [
    "STACKED_STEPS",
    "SeedFisherVectorProduct",
    "SeedLinearisation",
    "SeedProposals",
    "SeedSurrogates",
    "StackedCPOStep",
    "StackedNaturalPolicyStep",
    "StackedPCPOStep",
    "StackedTRPOStep",
    "StackedTrustRegionStep",
    "seed_conjugate_gradient",
    "seed_flat_grad",
    "seed_linearise",
]

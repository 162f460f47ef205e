"""The one declaration of which simulated muscles tune the model and which only validate it.

`TUNING`: the families (and seeds) the model's defaults, priors, knots and thresholds may be
chosen on; every family simulated before issue 47 is here, because each was looked at while
the defaults were chosen (`friction` chose the 75 kPa correction knot, Bouc-Wen was scored
beside the simulator's four from the start, the Duhem, generalized play and creep variants
were measured against the defaults as they changed). `VALIDATION`: muscles of kinds not
simulated before (loops that ratchet open, a width that grows with the pressure rate), run
only to report: no default may be chosen on them.

Both sets run the issue's path seeds 1-8: what is held out is the muscle, not the path (the
validation muscles were built after every default was fixed, so no seed of theirs was ever
seen), and the same seeds make the two tables comparable run for run.

A family belongs to the set that names it (a parameterised name, `duhem:30:60`, by its
prefix); pma_sim.registry checks that every registered family is in exactly one. Plain data:
nothing here imports the registry.
"""

from __future__ import annotations

from dataclasses import dataclass

SEEDS = tuple(range(1, 9))   # the seeds 1-8

# The simulator's own families, first of the tuning set: they take drift, and the tests that
# parametrize over "every family" run these.
SIMULATOR_FAMILIES = ('narrow', 'wide', 'asymmetric', 'creep')
BOUC_WEN = 'bouc-wen'
# The acceptance bench's default families (docs/model.md §3.1): the simulator's and Bouc-Wen.
ACCEPTANCE_FAMILIES = (*SIMULATOR_FAMILIES, BOUC_WEN)


@dataclass(frozen=True)
class MuscleSet:
    """A named set of scenario families (full names, parameters included) and path seeds."""

    name: str
    families: tuple[str, ...]
    seeds: tuple[int, ...]

    def names(self) -> frozenset[str]:
        """Its families' registry names (`duhem:30:60` -> `duhem`)."""
        return frozenset(family.partition(':')[0] for family in self.families)


TUNING = MuscleSet('tuning', (*ACCEPTANCE_FAMILIES, 'friction', 'gpi', 'duhem:30:60'), SEEDS)
VALIDATION = MuscleSet('validation', ('ratchet', 'rate-width'), SEEDS)
SETS = {muscle_set.name: muscle_set for muscle_set in (TUNING, VALIDATION)}


def set_of(family: str) -> MuscleSet:
    """The set a family (any name of it, `creep:wide:0.3:1.5` too) belongs to."""
    name = family.partition(':')[0]
    holding = [muscle_set for muscle_set in SETS.values() if name in muscle_set.names()]
    if len(holding) != 1:
        raise ValueError(f'{family!r} is in {len(holding)} of the declared sets, not one')
    return holding[0]

"""The known domains by name, and dataset generation by name."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType

from .base import Dataset, Domain, sample_dataset
from .quadrotor import QUADROTOR
from .robotaxi import VEHICLE
from .vtol import VTOL
from .warehouse import WAREHOUSE

DOMAINS: Mapping[str, Domain] = MappingProxyType(
    {d.name: d for d in (WAREHOUSE, VEHICLE, VTOL, QUADROTOR)}
)


def get_domain(name: str) -> Domain:
    """The domain called ``name``; a ValueError names the known ones otherwise."""
    try:
        return DOMAINS[name]
    except KeyError:
        raise ValueError(
            f"unknown domain {name!r}; known domains: {', '.join(sorted(DOMAINS))}"
        ) from None


def generate(
    name: str,
    *,
    seed: int = 0,
    n_nominal: int | None = None,
    n_anomaly: int | None = None,
    concepts: Sequence[str] | None = None,
) -> Dataset:
    """A labelled dataset of domain ``name`` (see :func:`base.sample_dataset`).

    Default sizes (nominal + anomaly): warehouse 1200 + 351, vehicle 640 + 200,
    vtol 4000 + 1000, quadrotor 300 + 100. ``concepts`` restricts the nominal
    samples to a subset of the nominal concepts (see :func:`concept_subset`).
    """
    return sample_dataset(
        get_domain(name), seed=seed, n_nominal=n_nominal, n_anomaly=n_anomaly, concepts=concepts
    )

"""How measurements reach the edge: on time, late, or not at all (pure, deterministic from a generator).

A vehicle sends a batch when the last epoch of it has happened; a measurement is in the first batch sent
at or after it *arrived*. In order, every measurement arrives at its own time. Late: a fraction of the
measurements of some kinds (the RSUs' ranges and bearings, which come through the RSU's backhaul) arrive
a uniform delay later, and so land in a later batch than their epoch's. Dropping them is what a client
without a lag window would have to do: a measurement that missed its epoch's batch is never sent.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgepos.core.observations import Observation


@dataclass(frozen=True)
class LateDelivery:
    """``fraction`` of the measurements of ``kinds`` arrive late by a delay uniform in
    [``min_delay_s``, ``max_delay_s``]."""

    fraction: float
    max_delay_s: float
    min_delay_s: float = 0.05
    kinds: tuple[str, ...] = ("rsu",)

    def __post_init__(self) -> None:
        if not 0.0 <= self.fraction <= 1.0:
            raise ValueError(f"the late fraction must be in [0, 1], got {self.fraction}")
        if not 0.0 <= self.min_delay_s <= self.max_delay_s:
            raise ValueError(f"delays must satisfy 0 <= min ({self.min_delay_s}) <= max ({self.max_delay_s})")


def add_delivery_arguments(parser: argparse.ArgumentParser, fraction_help: str) -> None:
    """``--delay-fraction`` (help: ``fraction_help``), ``--max-delay`` and ``--min-delay``: the command-line
    form of a :class:`LateDelivery` (see :func:`delivery_from`)."""
    parser.add_argument("--delay-fraction", metavar="F", type=float, default=None, help=fraction_help)
    parser.add_argument(
        "--max-delay",
        metavar="S",
        type=float,
        default=0.5,
        help="late RSU measurements arrive a uniform delay in [--min-delay, S] seconds late (default 0.5)",
    )
    parser.add_argument(
        "--min-delay", metavar="S", type=float, default=0.05, help="see --max-delay (default 0.05)"
    )


def delivery_from(args: argparse.Namespace) -> LateDelivery | None:
    """The late delivery the arguments ask for (None without ``--delay-fraction``); ValueError if out of range."""
    if args.delay_fraction is None:
        return None
    return LateDelivery(args.delay_fraction, args.max_delay, args.min_delay)


def arrival_times(
    observations: Sequence[Observation], delivery: LateDelivery, rng: np.random.Generator
) -> np.ndarray:
    """When each observation reaches the edge (s, the vehicle's clock). Draws one uniform per
    observation for lateness and one for the delay, so the draws do not depend on the kinds chosen."""
    times = np.array([o.t for o in observations], dtype=float)
    late = rng.random(times.size) < delivery.fraction
    delays = rng.uniform(delivery.min_delay_s, delivery.max_delay_s, times.size)
    eligible = np.array([o.kind in delivery.kinds for o in observations], dtype=bool)
    return times + np.where(late & eligible, delays, 0.0)


def _send_times(observations: Sequence[Observation], batch_epochs: int) -> list[float]:
    """The time each batch is sent: the time of its last epoch."""
    epochs = sorted({o.t for o in observations})
    return [epochs[min(i + batch_epochs, len(epochs)) - 1] for i in range(0, len(epochs), batch_epochs)]


def in_order_batches(observations: Sequence[Observation], batch_epochs: int) -> list[list[Observation]]:
    """Batches of ``batch_epochs`` epochs, every measurement in its epoch's batch."""
    sends = _send_times(observations, batch_epochs)
    batches: list[list[Observation]] = [[] for _ in sends]
    for observation in sorted(observations, key=lambda o: o.t):
        batches[int(np.searchsorted(sends, observation.t, side="left"))].append(observation)
    return batches


def arrival_batches(
    observations: Sequence[Observation], arrivals: np.ndarray, batch_epochs: int, drop_late: bool = False
) -> list[list[Observation]]:
    """Batches as sent: each holds what arrived since the previous one was sent, in arrival order; the
    measurements still in flight after the last epoch follow in one more batch. ``drop_late``: a
    measurement that missed its own epoch's batch is dropped instead (a client without a lag window)."""
    sends = _send_times(observations, batch_epochs)
    order = np.argsort(arrivals, kind="stable")
    batches: list[list[Observation]] = [[] for _ in range(len(sends) + 1)]
    for index in order:
        observation = observations[int(index)]
        slot = int(np.searchsorted(sends, arrivals[index] - 1e-9, side="left"))
        own = int(np.searchsorted(sends, observation.t - 1e-9, side="left"))
        if drop_late and slot != own:
            continue
        batches[slot].append(observation)
    return [batch for batch in batches if batch]

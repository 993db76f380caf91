"""Grouping a batch's observations into epochs: what every pipeline does first."""

from __future__ import annotations

from collections.abc import Sequence

from edgepos.core.observations import Observation


def group_by_time(observations: Sequence[Observation]) -> list[list[int]]:
    """Indices of the observations grouped by timestamp, in time order (stable within an epoch)."""
    order = sorted(range(len(observations)), key=lambda i: observations[i].t)
    epochs: list[list[int]] = []
    for index in order:
        if epochs and observations[epochs[-1][0]].t == observations[index].t:
            epochs[-1].append(index)
        else:
            epochs.append([index])
    return epochs

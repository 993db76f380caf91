"""Grouping a batch's observations into epochs: what every pipeline does first."""

from __future__ import annotations

from collections.abc import Sequence

from edgepos.core.observations import Observation


def group_by_time(observations: Sequence[Observation]) -> list[list[int]]:
    """Indices of the observations grouped by timestamp, in time order (stable within an epoch).

    The times are read once into a list. A batch already in time order (the usual one) is grouped in
    that one pass; any other (NaN included) is sorted, the sort keyed on the list without a Python
    function per observation (half the time of a ``lambda`` key and ``.t`` reads, a 100-observation
    batch). Both give the same groups where both apply."""
    times = [observation.t for observation in observations]
    in_order = _grouped_in_order(times)
    if in_order is not None:
        return in_order
    epochs: list[list[int]] = []
    last: float | None = None
    for index in sorted(range(len(times)), key=times.__getitem__):
        t = times[index]
        if epochs and t == last:
            epochs[-1].append(index)
        else:
            epochs.append([index])
            last = t
    return epochs


def _grouped_in_order(times: list[float]) -> list[list[int]] | None:
    """``group_by_time``'s groups of ``times`` in one pass when they never decrease; None when one does
    (or one is NaN, which compares neither equal nor greater)."""
    if not times:
        return []
    last = times[0]
    group = [0]
    epochs = [group]
    for index in range(1, len(times)):
        t = times[index]
        if t == last:
            group.append(index)
        elif t > last:
            group = [index]
            epochs.append(group)
            last = t
        else:
            return None
    return epochs

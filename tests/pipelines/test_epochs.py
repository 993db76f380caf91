"""``pipelines.epochs.group_by_time``: its one-pass grouping of a batch in time order against the sort."""

from __future__ import annotations

import math

from edgepos.core.observations import GyroObservation
from edgepos.pipelines.epochs import group_by_time
from hypothesis import given
from hypothesis import strategies as st


def sorted_groups(times: list[float]) -> list[list[int]]:
    """The reference: indices stably sorted by time, a new group wherever the time differs from the group's."""
    groups: list[list[int]] = []
    for index in sorted(range(len(times)), key=times.__getitem__):
        if groups and times[index] == times[groups[-1][0]]:
            groups[-1].append(index)
        else:
            groups.append([index])
    return groups


TIMES = st.sampled_from([0.0, -0.0, 0.05, 0.1, 0.1 + 1e-12, 1e9, math.nan, math.inf])


@given(st.lists(TIMES, max_size=12), st.booleans())
def test_groups_are_the_sorts(times, in_order):
    """In time order (the one-pass path) or not (the sort), NaN, signed zeros and ties included."""
    if in_order:
        times = sorted(t for t in times if not math.isnan(t))
    observations = [GyroObservation(t=t, yaw_rate=0.0) for t in times]
    assert group_by_time(observations) == sorted_groups(times)


def test_a_batch_in_time_order_and_one_out_of_it():
    observations = [GyroObservation(t=t, yaw_rate=0.0) for t in (0.1, 0.1, 0.2, 0.3, 0.3, 0.3)]
    assert group_by_time(observations) == [[0, 1], [2], [3, 4, 5]]
    assert group_by_time(observations[::-1]) == [[4, 5], [3], [0, 1, 2]]
    assert group_by_time([]) == []

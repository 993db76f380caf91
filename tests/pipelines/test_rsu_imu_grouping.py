"""``batch_epochs``'s compiled grouping (``core.kernels_grouping.group_epochs``) against its Python
reference (``reference_epochs``: ``group_by_time`` and ``epoch_parts`` epoch by epoch): the same epochs,
RSUs in use, gyros, records and rows for batches in and out of time order, with ties in time and range,
RSUs beyond their radius and more RSUs in view than ``max_rsus``; and a run's records (``fix_records``)
as ``epoch_parts`` and ``used`` give them."""

from __future__ import annotations

import numpy as np
import pytest
from edgepos.core.compiled import compiled_enabled
from edgepos.core.observations import GyroObservation, Observation, RsuObservation
from edgepos.pipelines.base import Rsu, StaticEnvironment
from edgepos.pipelines.epochs import group_by_time
from edgepos.pipelines.registry import get_pipeline
from edgepos.pipelines.rsu_imu_batch import BatchEpochs, batch_epochs, read_batch, reference_epochs
from edgepos.pipelines.rsu_imu_run import fix_records, used
from hypothesis import given, settings
from hypothesis import strategies as st

ENV = StaticEnvironment(
    {
        "A": Rsu("A", 0.0, -4.0),
        "B": Rsu("B", 50.0, 15.0, radius=40.0),
        "C": Rsu("C", 100.0, -4.0),
        "D": Rsu("D", 150.0, 15.0, radius=90.0),
        "E": Rsu("E", 200.0, -4.0),
    }
)
PIPELINE = get_pipeline("rsu_imu").inner.inner  # type: ignore[attr-defined]  # the registry's wrappers


def same_epochs(a: BatchEpochs, b: BatchEpochs) -> None:
    assert (a.times, a.order, a.bounds, a.starts, a.gyro_starts) == (
        b.times,
        b.order,
        b.bounds,
        b.starts,
        b.gyro_starts,
    )
    assert a.uses == b.uses
    assert np.array_equal(a.slots, b.slots) and a.slots.dtype == b.slots.dtype == np.int64
    for name in (
        "indices",
        "gyro_indices",
        "starts",
        "gyro_starts",
        "stations",
        "positions",
        "observed",
        "range_std",
        "bearing_std",
        "range_variances",
        "bearing_variances",
        "yaw_rates",
    ):
        got, want = getattr(a.rows, name), getattr(b.rows, name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    for k in range(len(a)):
        got, want = a.part(k), b.part(k)
        assert (got.indices, got.candidates, got.gyros, got.uses) == (
            want.indices,
            want.candidates,
            want.gyros,
            want.uses,
        )


observation = st.one_of(
    st.builds(
        RsuObservation,
        st.sampled_from([10.0, 10.05, 10.1, 10.15]),
        st.sampled_from(sorted(ENV.rsus)),
        st.sampled_from([0.0, 5.0, 30.0, 30.0, 45.0, 80.0, 120.0, 170.0]),  # ties, radius edges
        st.floats(-3.0, 3.0),
    ),
    st.builds(GyroObservation, st.sampled_from([10.0, 10.05, 10.1, 10.15]), st.floats(-1.0, 1.0)),
)


@pytest.mark.skipif(not compiled_enabled(), reason="the compiled grouping is off (EDGEPOS_NUMBA=0)")
@settings(max_examples=300, deadline=None)
@given(st.lists(observation, max_size=30), st.integers(1, 6), st.sampled_from(["joint", "average"]))
def test_the_compiled_grouping_gives_the_references_epochs(
    observations: list[Observation], max_rsus: int, handling: str
) -> None:
    options = PIPELINE.resolve_options({"max_rsus": max_rsus, "rsu_handling": handling})
    batch = read_batch(options, None, observations, ENV)
    epochs = batch_epochs(observations, batch, options)
    reference = reference_epochs(observations, batch, options)
    same_epochs(epochs, reference)
    assert [epochs.part(k).indices for k in range(len(epochs))] == group_by_time(observations)
    # a run's records: each index's, in each epoch's order, as epoch_parts and used give them
    records = fix_records(epochs, observations)
    for k in range(len(epochs)):
        part = reference.part(k)
        expected = {**part.uses, **{i: used(i, observations[i].kind) for i in part.candidates + part.gyros}}
        assert records[epochs.bounds[k] : epochs.bounds[k + 1]] == [expected[i] for i in part.indices]


def test_an_empty_batch_has_no_epochs() -> None:
    options = PIPELINE.resolve_options({})
    batch = read_batch(options, None, [], ENV)
    epochs = batch_epochs([], batch, options)
    assert len(epochs) == 0 and epochs.bounds == [0] and fix_records(epochs, []) == []
    same_epochs(epochs, reference_epochs([], batch, options))


def test_a_batch_beyond_the_kept_records_takes_new_ones() -> None:
    """Observations with indices past ``USED_KEPT`` have no slot: their records are made for them."""
    options = PIPELINE.resolve_options({})
    observations: list[Observation] = [GyroObservation(10.0 + 0.05 * (k // 2), 0.01) for k in range(4200)]
    observations[4150] = RsuObservation(observations[4150].t, "B", 60.0, 0.0)  # beyond B's 40 m
    batch = read_batch(options, None, observations, ENV)
    epochs = batch_epochs(observations, batch, options)
    same_epochs(epochs, reference_epochs(observations, batch, options))
    records = fix_records(epochs, observations)
    assert [r.index for r in records] == list(range(4200))
    assert records[4199] == used(4199, "gyro") and records[4150] == epochs.uses[4150]
    assert not records[4150].used and "40 m communication radius" in records[4150].reason

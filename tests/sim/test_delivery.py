"""sim.delivery: late arrivals only of the chosen kinds, by delays within bounds and about as often as asked;
batches in order keep every measurement in its epoch's batch; batches as sent hold every measurement
exactly once, in the first batch sent after it arrived (or, dropping late ones, exactly those that missed
their own batch are gone); LateDelivery refuses bad fractions and delays."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.sim.delivery import LateDelivery, arrival_batches, arrival_times, in_order_batches
from edgepos.sim.scenarios import rsu_imu_paper_scenario
from edgepos.sim.sensors import rsu_imu_epochs
from hypothesis import given, settings
from hypothesis import strategies as st

EPOCHS = rsu_imu_epochs(rsu_imu_paper_scenario(), np.random.default_rng([5, 0]))[:200]
OBSERVATIONS = [o for epoch in EPOCHS for o in epoch]
TIMES = np.array([o.t for o in OBSERVATIONS])
EPOCH_TIMES = sorted({o.t for o in OBSERVATIONS})
KINDS = np.array([o.kind for o in OBSERVATIONS])


def send_time_of(t: float, batch_epochs: int) -> float:
    """When the batch holding epoch ``t`` is sent: the time of that batch's last epoch."""
    k = EPOCH_TIMES.index(t)
    last = min((k // batch_epochs + 1) * batch_epochs, len(EPOCH_TIMES)) - 1
    return EPOCH_TIMES[last]


@settings(max_examples=40, deadline=None)
@given(
    fraction=st.floats(0.05, 0.95),
    low=st.just(0.0) | st.floats(0.01, 0.5),  # a delay far below the times' resolution would vanish
    span=st.floats(0.0, 1.5),
    kinds=st.sampled_from([("rsu",), ("gyro",), ("rsu", "gyro"), ()]),
    seed=st.integers(0, 2**32 - 1),
)
def test_only_the_chosen_kinds_are_delayed_within_bounds_about_as_often_as_asked(
    fraction, low, span, kinds, seed
):
    delivery = LateDelivery(fraction, low + span, low, kinds)
    arrivals = arrival_times(OBSERVATIONS, delivery, np.random.default_rng(seed))
    delays = arrivals - TIMES
    eligible = np.isin(KINDS, kinds)
    assert np.all(delays[~eligible] == 0.0)
    late = delays > 0.0 if low > 0.0 else delays != 0.0
    assert np.all(delays[late] >= low - 1e-12) and np.all(delays[late] <= low + span + 1e-12)
    assert np.all(delays >= 0.0)
    count = int(eligible.sum())
    if count and low > 0.0:  # a zero delay cannot be told from on time
        expected, sigma = count * fraction, math.sqrt(count * fraction * (1.0 - fraction))
        assert abs(int(late.sum()) - expected) <= 5.0 * sigma + 1.0, (late.sum(), expected, sigma)


@pytest.mark.parametrize("fraction", [0.0, 1.0])
def test_fraction_zero_delays_nothing_and_one_delays_every_chosen_measurement(fraction):
    arrivals = arrival_times(OBSERVATIONS, LateDelivery(fraction, 0.5, 0.1), np.random.default_rng(1))
    delays = arrivals - TIMES
    rsu = KINDS == "rsu"
    assert np.all(delays[~rsu] == 0.0)
    if fraction == 0.0:
        assert np.all(delays == 0.0)
    else:
        assert np.all((delays[rsu] >= 0.1) & (delays[rsu] <= 0.5))


def test_the_draws_do_not_depend_on_the_kinds_chosen():
    """One uniform per observation for lateness and one for the delay, whatever the kinds: the RSU delays
    are the same when the gyro is delayed too."""
    rsu_only = arrival_times(OBSERVATIONS, LateDelivery(0.3, 0.8), np.random.default_rng(9))
    both = arrival_times(
        OBSERVATIONS, LateDelivery(0.3, 0.8, kinds=("rsu", "gyro")), np.random.default_rng(9)
    )
    rsu = KINDS == "rsu"
    np.testing.assert_array_equal(rsu_only[rsu], both[rsu])
    assert np.any(both[~rsu] != TIMES[~rsu])


@pytest.mark.parametrize("batch_epochs", [1, 2, 3, 7, 200, 500])
def test_in_order_batches_keep_every_measurement_in_its_epochs_batch(batch_epochs):
    batches = in_order_batches(OBSERVATIONS, batch_epochs)
    assert len(batches) == math.ceil(len(EPOCH_TIMES) / batch_epochs)
    assert [id(o) for batch in batches for o in batch] == [id(o) for o in OBSERVATIONS]
    for j, batch in enumerate(batches):
        epochs = EPOCH_TIMES[j * batch_epochs : (j + 1) * batch_epochs]
        assert sorted({o.t for o in batch}) == epochs
    # With no delay, batches as sent are the batches in order.
    assert arrival_batches(OBSERVATIONS, TIMES.copy(), batch_epochs) == batches


@settings(max_examples=40, deadline=None)
@given(
    delays=st.dictionaries(st.integers(0, len(OBSERVATIONS) - 1), st.floats(0.0, 2.0), max_size=80),
    batch_epochs=st.integers(1, 6),
    drop_late=st.booleans(),
)
def test_batches_as_sent_hold_each_measurement_once_in_the_first_batch_after_it_arrived(
    delays, batch_epochs, drop_late
):
    arrivals = TIMES.copy()
    for index, delay in delays.items():
        arrivals[index] += delay
    batches = arrival_batches(OBSERVATIONS, arrivals, batch_epochs, drop_late=drop_late)
    index_of = {id(o): i for i, o in enumerate(OBSERVATIONS)}
    sent = [[index_of[id(o)] for o in batch] for batch in batches]
    flat = [i for batch in sent for i in batch]
    assert len(flat) == len(set(flat))  # nothing twice
    own = [send_time_of(o.t, batch_epochs) for o in OBSERVATIONS]
    missed = {i for i in range(len(OBSERVATIONS)) if arrivals[i] > own[i] + 1e-9}
    if drop_late:
        assert set(flat) == set(range(len(OBSERVATIONS))) - missed  # exactly those that missed their batch
    else:
        assert set(flat) == set(range(len(OBSERVATIONS)))
    sends = sorted({send_time_of(t, batch_epochs) for t in EPOCH_TIMES})
    for batch in sent:
        assert np.all(np.diff(arrivals[batch]) >= 0.0)  # in arrival order
        # Every measurement of a batch arrived after the send before it and by its own (or after the last
        # epoch: the batch of what was still in flight).
        send = min((s for s in sends if s >= arrivals[batch].max() - 1e-9), default=math.inf)
        previous = max((s for s in sends if s < send), default=-math.inf)
        assert all(previous < arrivals[i] - 1e-9 <= send for i in batch)
    assert all(batches)


def test_a_measurement_still_in_flight_after_the_last_epoch_comes_in_a_last_batch_of_its_own():
    arrivals = TIMES.copy()
    arrivals[-1] += 0.3  # the last epoch's gyro
    batches = arrival_batches(OBSERVATIONS, arrivals, 4)
    assert batches[-1] == [OBSERVATIONS[-1]]
    assert arrival_batches(OBSERVATIONS, arrivals, 4, drop_late=True) == batches[:-1]


@pytest.mark.parametrize(
    "arguments",
    [
        (-0.1, 1.0),
        (1.01, 1.0),
        (math.nan, 1.0),
        (0.5, 0.01),
        (0.5, 1.0, -0.1),
        (0.5, math.nan),
        (0.5, 1.0, 1.5),
    ],
)
def test_late_delivery_refuses_bad_fractions_and_delays(arguments):
    with pytest.raises(ValueError):
        LateDelivery(*arguments)


def test_late_delivery_takes_the_bounds_themselves():
    for arguments in ((0.0, 0.0, 0.0), (1.0, 0.3, 0.3), (0.5, 10.0)):
        LateDelivery(*arguments)

"""The simulated carrier phase (sim.gnss_carrier): the phase is the path in cycles plus an integer ambiguity
that changes only at a new lock (LLI set) or an unflagged slip; the lock chain holds the recording's phase
fraction and loss-of-lock rate; and adding the phase leaves every pseudorange of a run as it was."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.orbits import SPEED_OF_LIGHT
from edgepos.sim.gnss_carrier import (
    LOSS_OF_LOCK_RATE,
    PHASE_FRACTION,
    PHASE_LOCK_CN0_DBHZ,
    CarrierModel,
    CarrierPhase,
    carrier_phase,
    draw,
)
from edgepos.sim.gnss_scenario import urban_scenario
from edgepos.sim.gnss_sensors import simulate

FREQUENCY = np.array([1575.42e6, 1561.098e6])


def _phase(model: CarrierModel, cn0: float, epochs: int, seed: int = 3) -> tuple[CarrierPhase, np.ndarray]:
    rng = np.random.default_rng(seed)
    shape = (epochs, 2)
    draws = dataclasses.replace(draw(rng, shape, model), noise=np.zeros(shape))
    path = 2.0e7 + np.arange(epochs)[:, None] * np.array([[120.0, -80.0]])
    out = carrier_phase(
        draws, model, np.ones(shape, bool), np.full(shape, cn0), path, np.zeros(shape), FREQUENCY
    )
    return out, path / (SPEED_OF_LIGHT / FREQUENCY)[None, :]


def test_the_ambiguity_is_an_integer_that_changes_only_where_lock_is_lost() -> None:
    model = CarrierModel(phase_multipath_m=0.0, unflagged_slip_probability=0.0)
    out, cycles = _phase(model, 40.0, 3000)
    locked = np.isfinite(out.cycles)
    ambiguity = out.cycles - cycles
    assert np.allclose(ambiguity[locked], np.round(ambiguity[locked]), atol=1e-4)
    for j in range(2):
        for k in range(1, 3000):
            if locked[k, j] and locked[k - 1, j] and not out.lli[k, j]:
                assert ambiguity[k, j] == pytest.approx(ambiguity[k - 1, j], abs=1e-4)
    assert out.lli[~locked].sum() == 0


def test_an_unflagged_slip_jumps_by_whole_cycles_without_lli() -> None:
    model = CarrierModel(phase_multipath_m=0.0, unflagged_slip_probability=1.0)
    out, cycles = _phase(model, 50.0, 400)
    ambiguity = out.cycles - cycles
    both = np.isfinite(ambiguity[1:]) & np.isfinite(ambiguity[:-1]) & (out.lli[1:] == 0)
    jumps = np.abs(np.diff(ambiguity, axis=0))[both]
    assert jumps.size > 100 and np.all(np.round(jumps) >= 1) and np.all(np.round(jumps) <= 20)


@pytest.mark.parametrize("bin_index", [2, 3, 5])
def test_the_lock_chain_holds_the_recordings_phase_fraction_and_loss_rate(bin_index: int) -> None:
    cn0 = float(PHASE_LOCK_CN0_DBHZ[bin_index])
    out, _ = _phase(CarrierModel(), cn0, 40_000, seed=bin_index)
    locked = np.isfinite(out.cycles)
    assert locked.mean() == pytest.approx(PHASE_FRACTION[bin_index], abs=0.03)
    assert out.lli[locked].mean() == pytest.approx(LOSS_OF_LOCK_RATE[bin_index], rel=0.15)


def test_the_phase_leaves_the_pseudoranges_as_they_were() -> None:
    scenario = dataclasses.replace(
        urban_scenario(short=True), doppler=None
    )  # its draws come after the phase's
    with_phase = simulate(scenario, np.random.default_rng([1, 0])).observations
    without = simulate(
        dataclasses.replace(scenario, carrier=None), np.random.default_rng([1, 0])
    ).observations
    codes = [o for o in with_phase if isinstance(o, PseudorangeObservation)]
    assert [dataclasses.replace(o, carrier_cycles=None, lli=None) for o in codes] == [
        o for o in without if isinstance(o, PseudorangeObservation)
    ]
    assert sum(o.carrier_cycles is not None for o in codes) > len(codes) / 3
    assert all(o.carrier_cycles is None or o.lli in (0, 1) for o in codes)

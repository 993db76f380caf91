"""Filter-based solution separation (core.integrity_bank): exact state bytes, chi-square separations
without a fault, a slowly growing fault detected, and the protection level against Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.integrity import OK, IntegrityBudget
from edgepos.core.integrity_bank import RangeBearing, SeparationBank, protect_with_bank

RSUS = {"A": (0.0, 30.0), "B": (60.0, -25.0), "C": (120.0, 20.0)}
RANGE_STD, BEARING_STD = 0.6, math.radians(0.5)
PERIOD = 0.05


def _drive(seed: int, epochs: int, ramp: tuple[str, float, int] | None = None, risk: float = 1e-5):
    """A vehicle at 15 m/s along x past three RSUs, the bank over ``epochs`` epochs; ``ramp``: (RSU, range
    growth m per epoch, first epoch) of a fault. Yields per epoch the reference error, the protection of
    the reference's own position and the RSU whose test failed."""
    rng = np.random.default_rng(seed)
    budget = IntegrityBudget(risk, 1e-4, 1e-2, 10.0)
    bank = SeparationBank.start(
        np.array([0.0, 15.0, 0.0, 0.0, 0.0, 0.0]), np.diag([1.0, 1.0, 9.0, 1.0, 1.0, 9.0]), 0.0
    )
    for k in range(1, epochs + 1):
        t = k * PERIOD
        truth = np.array([15.0 * t, 0.0])
        measurements = []
        for rsu, (x, y) in RSUS.items():
            dx, dy = truth[0] - x, truth[1] - y
            distance = math.hypot(dx, dy) + rng.normal(0.0, RANGE_STD)
            if ramp is not None and rsu == ramp[0] and k >= ramp[2]:
                distance += ramp[1] * (k - ramp[2])
            bearing = math.atan2(dy, dx) + rng.normal(0.0, BEARING_STD)
            measurements.append(RangeBearing(rsu, x, y, distance, bearing, RANGE_STD, BEARING_STD))
        bank.predict(t, 10.0)
        bank.spawn([m.rsu_id for m in measurements])
        bank.update(measurements)
        position = bank.means[0, [0, 3]]
        protection, faulty = protect_with_bank(position, bank.covs[0][np.ix_([0, 3], [0, 3])], bank, budget)
        yield float(np.hypot(*(position - truth))), protection, faulty, bank


def test_bank_bytes_round_trip_exactly():
    *_, (_, _, _, bank) = _drive(1, 30)
    bank.exclude("B", 7.25)
    blob = bank.to_bytes()
    again = SeparationBank.from_bytes(blob)
    assert again.to_bytes() == blob
    assert again.ids == bank.ids and again.excluded == {"B": 7.25} and again.t == bank.t
    assert np.array_equal(again.means, bank.means) and np.array_equal(again.covs, bank.covs)
    with pytest.raises(ValueError):
        SeparationBank.from_bytes(blob[:-1])


def test_separations_are_chi_square_with_two_dof_without_a_fault():
    squares = []
    for seed in range(8):
        for k, (_, _, _, bank) in enumerate(_drive(seed, 200)):
            if k >= 20:
                squares.extend(bank.separations()[0] ** 2)
    squares = np.array(squares)
    assert squares.size > 1000
    assert 1.6 < squares.mean() < 2.4  # chi-square 2 dof: mean 2 (the samples are correlated in time)
    assert np.mean(squares > 9.21) < 0.02  # its 99 % quantile


def test_a_slowly_growing_range_fault_is_detected_and_bounded_until_then():
    ramp = ("B", 0.02, 40)  # 2 cm per epoch: 0.4 m/s, under any one epoch's threshold
    detected = None
    for k, (error, protection, faulty, _) in enumerate(_drive(5, 200, ramp)):
        if faulty is not None:
            detected = (k, faulty)
            break
        assert protection.state != OK or error <= protection.level, (k, error, protection)
    assert detected is not None, "the fault was never detected"
    # with three RSUs the fault moves the others' sub-filters too, so the worst test may name another RSU;
    # B's own separation is then past the threshold as well
    *_, (_, _, _, bank) = _drive(5, detected[0] + 1, ramp)
    statistics = dict(zip(bank.ids[1:], bank.separations()[0], strict=True))
    assert statistics["B"] > 4.0, statistics
    # nothing is detected in the same run without the fault
    assert all(faulty is None for _, _, faulty, _ in _drive(5, 200))


def test_protection_level_bounds_the_error_by_monte_carlo_and_is_not_vacuous():
    errors, levels = [], []
    for seed in range(20):
        for k, (error, protection, _, _) in enumerate(_drive(100 + seed, 120, risk=0.02)):
            if k >= 20:
                errors.append(error)
                levels.append(protection.level)
    errors, levels = np.array(errors), np.array(levels)
    assert np.mean(errors > levels) <= 0.02
    assert np.median(levels) < 6.0 * math.sqrt(np.mean(errors**2))


def test_the_compiled_kernels_match_the_numpy_reference():
    import copy

    *_, (_, _, _, bank) = _drive(3, 40)
    measurements = [
        RangeBearing("A", 0.0, 30.0, 31.0, -1.2, RANGE_STD, BEARING_STD),
        RangeBearing("B", 60.0, -25.0, 40.0, 2.1, RANGE_STD, BEARING_STD),
        RangeBearing("D", -40.0, 25.0, 70.0, -0.4, RANGE_STD, BEARING_STD),
    ]
    bank.predict(bank.t + PERIOD, 10.0)
    bank.spawn(["D"])
    reference = copy.deepcopy(bank)
    bank.update(measurements)
    reference.update_reference(measurements)
    assert np.allclose(bank.means, reference.means, rtol=0, atol=1e-9)
    assert np.allclose(bank.covs, reference.covs, rtol=0, atol=1e-12)
    for compiled, numpy_form in zip(bank.separations(), bank.separations_reference(), strict=True):
        assert np.allclose(compiled, numpy_form, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dt", [PERIOD, 0.0493, 1e-3, 2.5])
def test_the_compiled_prediction_matches_the_numpy_reference(dt: float) -> None:
    """``bank_predict`` (F and Q written out block by block) gives the numpy ``predict_reference``'s
    means and covariances to rounding, the bank's own after 40 epochs and a random one."""
    import copy

    *_, (_, _, _, driven) = _drive(3, 40)
    rng = np.random.default_rng(4)
    roots = rng.standard_normal((4, 6, 6))
    drawn = SeparationBank(
        ["", "A", "B", "C"], 50.0 * rng.standard_normal((4, 6)), roots @ roots.transpose(0, 2, 1), 0.0
    )
    for bank in (driven, drawn):
        reference = copy.deepcopy(bank)
        bank.predict(bank.t + dt, 10.0)
        reference.predict_reference(dt, 10.0)
        scale = np.abs(reference.covs).max()
        assert np.allclose(bank.means, reference.means, rtol=1e-13, atol=1e-12)
        assert np.allclose(bank.covs, reference.covs, rtol=1e-13, atol=1e-13 * scale)


def _numpy_bank(monkeypatch: pytest.MonkeyPatch) -> None:
    """Run the bank on its numpy reference (the kernels off), as a service without numba would."""
    import edgepos.core.integrity_bank as module

    monkeypatch.setattr(module, "_compiled", lambda: False)


@pytest.mark.parametrize("excluded", [False, True])
def test_one_compiled_epoch_equals_the_numpy_steps(monkeypatch: pytest.MonkeyPatch, excluded: bool) -> None:
    """``SeparationBank.step`` (one kernel call: predict, spawn, update, protect) gives the bank and the
    protection that the numpy predict, spawn, update and ``protect_with_bank`` give, a failed test too."""
    import copy

    *_, (_, _, _, bank) = _drive(3, 40)
    if excluded:
        bank.exclude("B", 99.0)
    budget = IntegrityBudget(1e-5, 1e-4, 1e-2, 10.0)
    ids = ["A", "B", "D"]
    arrays = (
        np.array([[0.0, 30.0], [60.0, -25.0], [-40.0, 25.0]]),
        np.array([[31.0, -1.2], [47.0, 2.1], [70.0, -0.4]]),  # B's range 7 m off: its test fails
        np.full(3, RANGE_STD),
        np.full(3, BEARING_STD),
    )
    reference = copy.deepcopy(bank)
    fix = (float(bank.means[0, 0]) + 0.3, float(bank.means[0, 3]) - 0.2, 0.04, 0.002, 0.05)
    compiled = bank.step(bank.t + PERIOD, 10.0, ids, arrays, fix, budget)
    _numpy_bank(monkeypatch)
    expected = reference.step(reference.t + PERIOD, 10.0, ids, arrays, fix, budget)
    assert bank.ids == reference.ids == ["", "A", "B", "C", "D"]
    assert np.allclose(bank.means, reference.means, rtol=0, atol=1e-9)
    assert np.allclose(bank.covs, reference.covs, rtol=0, atol=1e-12)
    assert compiled[1] == expected[1] is not None  # with B held out, the test points at another RSU
    assert not excluded or compiled[1] != "B"  # an excluded RSU's failed test is not reported again
    assert compiled[0].state == expected[0].state and compiled[0].faulty == expected[0].faulty
    assert compiled[0].level == pytest.approx(expected[0].level, rel=1e-12)
    assert compiled[0].statistic == pytest.approx(expected[0].statistic, rel=1e-9)


def test_a_fix_without_a_proper_covariance_has_no_bound_and_the_bank_steps_on() -> None:
    *_, (_, _, _, bank) = _drive(3, 5)
    arrays = (
        np.array([[0.0, 30.0]]),
        np.array([[31.0, -1.2]]),
        np.full(1, RANGE_STD),
        np.full(1, BEARING_STD),
    )
    t = bank.t + PERIOD
    protection, faulty = bank.step(
        t, 10.0, ["A"], arrays, (0.0, 0.0, 1.0, 2.0, 1.0), IntegrityBudget(1e-5, 1e-4, 1e-2, 10.0)
    )
    assert protection.level is None and protection.state == "unavailable" and faulty is None
    assert bank.t == t


def test_epochs_on_the_kept_plan_equal_the_numpy_steps_as_the_rsus_change(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``SeparationBank.epoch`` keeps what the kernel needs between epochs (``_Plan``) and rebuilds it when
    an RSU comes or goes, one is excluded or its exclusion ends: epoch by epoch the bank and the
    protection equal the numpy steps', and the bytes round-trip with the plan left out."""
    import copy

    import edgepos.core.integrity_bank as module

    *_, (_, _, _, bank) = _drive(3, 40)
    numpy_bank = copy.deepcopy(bank)
    budget = IntegrityBudget(1e-5, 1e-4, 1e-2, 10.0)
    sites = {**RSUS, "D": (-40.0, 25.0)}
    heard = [["A", "B", "C"]] * 4 + [["A", "B", "C", "D"]] * 4 + [["A", "D"]] * 6 + [["A", "B", "D"]] * 4
    rng = np.random.default_rng(9)
    plan, rebuilt = None, 0
    for k, ids in enumerate(heard):
        t = bank.t + PERIOD
        truth = (15.0 * t, 0.0)
        positions = np.array([sites[rsu] for rsu in ids])
        dx, dy = truth[0] - positions[:, 0], truth[1] - positions[:, 1]
        observed = np.column_stack(
            [np.hypot(dx, dy) + rng.normal(0.0, RANGE_STD, len(ids)), np.arctan2(dy, dx)]
        )
        arrays = (positions, observed, np.full(len(ids), RANGE_STD), np.full(len(ids), BEARING_STD))
        if k == 10:
            bank.exclude("C", t + 3 * PERIOD)
            numpy_bank.exclude("C", t + 3 * PERIOD)
        for each in (bank, numpy_bank):
            each.excluded_now(t)
        # the reported estimate: 8 states with x and y at 0 and 3, as the pipeline's output
        mean = np.zeros(8)
        mean[[0, 3]] = bank.means[0, [0, 3]] + [0.1, -0.05]
        cov = np.eye(8) * 0.05
        cov[0, 3] = cov[3, 0] = 0.004
        compiled = bank.epoch(t, 10.0, ids, arrays, mean, cov, (0, 3), budget)
        rebuilt += bank._plan is not plan
        plan = bank._plan
        monkeypatch.setattr(module, "_compiled", lambda: False)
        expected = numpy_bank.epoch(t, 10.0, ids, arrays, mean, cov, (0, 3), budget)
        monkeypatch.undo()
        assert bank.ids == numpy_bank.ids and bank.t == numpy_bank.t, k
        assert np.allclose(bank.means, numpy_bank.means, rtol=0, atol=1e-9), k
        assert np.allclose(bank.covs, numpy_bank.covs, rtol=0, atol=1e-12), k
        assert compiled[1] == expected[1] and compiled[0].state == expected[0].state, k
        assert compiled[0].level == pytest.approx(expected[0].level, rel=1e-12), k
        bank.prune(ids)
        numpy_bank.prune(ids)
        assert bank.ids == numpy_bank.ids, k
    # kept while the RSUs stay; rebuilt at the first epoch, when D comes, when B and C go, at C's
    # exclusion and its end, when B is back (and whenever prune drops a sub-filter)
    assert 6 <= rebuilt < len(heard) // 2, rebuilt
    again = SeparationBank.from_bytes(bank.to_bytes())
    assert again._plan is None and again.to_bytes() == bank.to_bytes()


@pytest.mark.parametrize("compiled", [True, False])
def test_epoch_with_prune_equals_epoch_then_prune(monkeypatch: pytest.MonkeyPatch, compiled: bool) -> None:
    """``epoch(..., prune=True)`` (what the pipeline calls: the kernel counts the sub-filters prune would
    drop, so the usual epoch skips it) leaves the bank and gives the outcome that ``epoch`` then ``prune``
    give, epoch by epoch, as RSUs leave and their sub-filters converge and are dropped, and with a failed
    test (no prune then: the caller excludes first)."""
    import copy

    if not compiled:
        _numpy_bank(monkeypatch)
    *_, (_, _, _, bank) = _drive(3, 40)
    separate = copy.deepcopy(bank)
    budget = IntegrityBudget(1e-5, 1e-4, 1e-2, 10.0)
    sites = {**RSUS, "D": (-40.0, 25.0)}
    heard = [["A", "B", "C", "D"]] * 4 + [["A", "D"]] * 60 + [["A", "B", "D"]] * 4
    rng = np.random.default_rng(4)
    dropped = failed = 0
    for k, ids in enumerate(heard):
        t = bank.t + PERIOD
        truth = (15.0 * t, 0.0)
        positions = np.array([sites[rsu] for rsu in ids])
        dx, dy = truth[0] - positions[:, 0], truth[1] - positions[:, 1]
        ranges = np.hypot(dx, dy) + rng.normal(0.0, RANGE_STD, len(ids))
        if k == 66:
            ranges[ids.index("B")] += 8.0  # B's range biased: its test fails
        observed = np.column_stack([ranges, np.arctan2(dy, dx)])
        arrays = (positions, observed, np.full(len(ids), RANGE_STD), np.full(len(ids), BEARING_STD))
        mean = np.zeros(8)
        mean[[0, 3]] = bank.means[0, [0, 3]] + [0.1, -0.05]
        cov = np.eye(8) * 0.05
        cov[0, 3] = cov[3, 0] = 0.004
        count = len(bank.ids)
        together = bank.epoch(t, 10.0, ids, arrays, mean, cov, (0, 3), budget, prune=True)
        apart = separate.epoch(t, 10.0, ids, arrays, mean, cov, (0, 3), budget)
        if apart[1] is None:
            separate.prune(ids)
        dropped += len(bank.ids) < count
        failed += together[1] is not None
        assert together == apart, k
        assert bank.ids == separate.ids and bank.t == separate.t, k
        assert np.array_equal(bank.means, separate.means) and np.array_equal(bank.covs, separate.covs), k
    assert dropped >= 2 and failed >= 1, (dropped, failed)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_bank_with_a_value_not_finite_does_not_decode(
    monkeypatch: pytest.MonkeyPatch, compiled: bool
) -> None:
    if not compiled:
        _numpy_bank(monkeypatch)
    *_, (_, _, _, bank) = _drive(2, 10)
    blob = bank.to_bytes()
    assert SeparationBank.from_bytes(blob).to_bytes() == blob
    for value in (math.nan, math.inf, -math.inf):
        for at in (len(blob) - 8 * bank.covs.size - 8, len(blob) - 8):  # the last mean, the last covariance
            broken = blob[:at] + np.array([value], dtype="<f8").tobytes() + blob[at + 8 :]
            with pytest.raises(ValueError, match="not finite"):
                SeparationBank.from_bytes(broken)

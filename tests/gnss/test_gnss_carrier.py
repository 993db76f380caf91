"""Carrier-smoothed code (gnss.carrier): the Hatch filter against its closed form, each cycle-slip test
restarting only the satellite it concerns, and the tracks' exact serialisation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from edgepos.gnss.carrier import (
    CarrierTrack,
    HatchConfig,
    hatch_update,
    new_track,
    tracks_from_arrays,
    tracks_to_arrays,
)

LAMBDA = 299_792_458.0 / 1575.42e6
SATS = ("G05", "C21")


def _run(
    epochs: int,
    rate_mps: tuple[float, float] = (0.0, 0.0),
    config: HatchConfig | None = None,
    doppler: bool = True,
    seed: int = 7,
):
    """Two satellites, ranges changing at constant rates, code noise of 3 m, carrier exact up to its
    ambiguity; returns the tracks and per epoch (result, code, carrier cycles, doppler)."""
    config = config or HatchConfig()
    rng = np.random.default_rng(seed)
    ranges0 = np.array([2.2e7, 2.4e7])
    ambiguity = np.array([123456.0, -98765.0])  # cycles
    tracks: dict[str, CarrierTrack] = {}
    history = []
    for k in range(epochs):
        t = 1000.0 + k
        ranges = ranges0 + np.asarray(rate_mps) * k
        code = ranges + 3.0 * rng.standard_normal(2)
        cycles = ranges / LAMBDA + ambiguity
        dop = -np.asarray(rate_mps) / LAMBDA if doppler else np.full(2, np.nan)
        result = hatch_update(
            tracks, t, SATS, code, cycles, np.full(2, LAMBDA), dop, np.zeros(2, int), config
        )
        history.append((result, code, cycles, dop))
    return tracks, history


@pytest.mark.parametrize("rate", [(0.0, 0.0), (-450.0, 730.0)])
def test_smoothed_code_is_the_average_code_minus_carrier_plus_carrier(rate):
    """Within the window, S_k = mean_i (P_i - lambda L_i) + lambda L_k exactly (constant geometry, and a
    range changing as fast as a satellite's), and its error is the code noise divided by sqrt(k)."""
    _, history = _run(60, rate)
    codes = np.array([h[1] for h in history])
    phases = LAMBDA * np.array([h[2] for h in history])
    for k, (result, _, _, _) in enumerate(history):
        expected = np.mean(codes[: k + 1] - phases[: k + 1], axis=0) + phases[k]
        np.testing.assert_allclose(result.pseudorange_m, expected, rtol=0, atol=1e-6)
        assert list(result.count) == [k + 1, k + 1] and result.reset == [None, None]
    truth = 2.2e7 + rate[0] * 59
    assert abs(history[-1][0].pseudorange_m[0] - truth) < 4 * 3.0 / np.sqrt(60)


def test_the_window_caps_the_epochs_averaged():
    _, history = _run(30, config=HatchConfig(window_s=10.0))
    assert [h[0].count[0] for h in history[8:12]] == [9, 10, 10, 10]
    codes = np.array([h[1] for h in history])
    # Constant geometry: S_k = P_k / N + (N - 1) / N * S_{k-1} once capped.
    for k in range(10, 30):
        previous = history[k - 1][0].pseudorange_m
        np.testing.assert_allclose(history[k][0].pseudorange_m, codes[k] / 10 + 0.9 * previous, atol=1e-6)


def _continue(tracks, k, code_offset=(0.0, 0.0), cycle_offset=(0.0, 0.0), lli=(0, 0), doppler=True, dt=1.0):
    """One more epoch after ``_run`` (constant geometry) with offsets on code and carrier."""
    ranges = np.array([2.2e7, 2.4e7])
    cycles = ranges / LAMBDA + np.array([123456.0, -98765.0]) + np.asarray(cycle_offset)
    code = ranges + np.asarray(code_offset)
    t = 1000.0 + k - 1 + dt
    dop = np.zeros(2) if doppler else np.full(2, np.nan)
    return hatch_update(
        tracks, t, SATS, code, cycles, np.full(2, LAMBDA), dop, np.asarray(lli), HatchConfig()
    ), code


@pytest.mark.parametrize(
    ("kwargs", "reason"),
    [
        ({"lli": (0, 1)}, "loss of lock"),
        ({"cycle_offset": (0.0, 20.0)}, "off the Doppler"),  # 20 cycles, 3.8 m: the Doppler sees it
        ({"cycle_offset": (0.0, 200.0), "doppler": False}, "code-carrier jump"),  # 38 m, no Doppler
        ({"dt": 9.0}, "since its previous carrier phase"),
    ],
)
def test_a_slip_restarts_only_its_satellite(kwargs, reason):
    tracks, history = _run(20, doppler=kwargs.get("doppler", True))
    before = history[-1][0].pseudorange_m
    result, code = _continue(tracks, 20, **kwargs)
    gap = kwargs.get("dt", 1.0) > 1.0
    assert result.reset[1] is not None and reason in result.reset[1]
    assert result.count[1] == 1 and result.pseudorange_m[1] == code[1]  # restarted from its raw code
    assert tracks["C21"].count == 1
    if gap:
        assert result.count[0] == 1  # the gap is every satellite's
    else:
        assert result.reset[0] is None and result.count[0] == 21
        # G05 went on averaging: its new value is 1/21 of the way from the old to the new code.
        assert result.pseudorange_m[0] == pytest.approx(before[0] + (code[0] - before[0]) / 21, abs=1e-6)


def test_small_slips_without_doppler_pass_and_each_test_has_its_threshold():
    """Without Doppler a 2-cycle slip (0.4 m) is below the code-carrier test: documented, not a failure."""
    tracks, _ = _run(20, doppler=False)
    result, _ = _continue(tracks, 20, cycle_offset=(0.0, 2.0), doppler=False)
    assert result.reset == [None, None]
    tracks, _ = _run(20)
    result, _ = _continue(tracks, 20, cycle_offset=(0.0, 4.0))  # 4 cycles in 1 s: under 5 cycles/s
    assert result.reset == [None, None]


def test_rows_without_carrier_pass_their_code_and_old_tracks_are_dropped():
    tracks, _ = _run(5)
    code = np.array([2.2e7 + 1.0, 2.4e7 - 1.0])
    result = hatch_update(
        tracks,
        1005.0,
        SATS,
        code,
        np.array([np.nan, np.nan]),
        np.full(2, LAMBDA),
        np.zeros(2),
        np.zeros(2, int),
        HatchConfig(),
    )
    assert list(result.pseudorange_m) == list(code) and list(result.count) == [0, 0]
    assert set(tracks) == set(SATS)  # kept: a later phase within the gap continues them
    hatch_update(
        tracks,
        1010.0,
        (),
        np.zeros(0),
        np.zeros(0),
        np.zeros(0),
        np.zeros(0),
        np.zeros(0, int),
        HatchConfig(),
    )
    assert tracks == {}


def test_tracks_round_trip_exactly():
    tracks, _ = _run(7, (-450.0, 730.0))
    tracks["E11"] = CarrierTrack(1003.5, 3.0, 2.5e7 + 0.1, -1.0e9 + 0.001, None)
    sats, table = tracks_to_arrays(tracks)
    again = tracks_from_arrays(sats, table)
    assert again == tracks and again["E11"].doppler_hz is None
    assert tracks_to_arrays(again)[1].tobytes() == table.tobytes()


def test_new_track_is_the_constructors() -> None:
    """``new_track`` builds a track without the frozen ``__init__``: valid only while CarrierTrack has no
    ``__post_init__`` and no slots; the same fields, equal to the constructor's, still frozen."""
    assert not hasattr(CarrierTrack, "__post_init__") and not hasattr(CarrierTrack, "__slots__")
    for doppler in (None, -1234.5):
        made = new_track(12.5, 3.0, 2.2e7, 1.1e8, doppler)
        assert made == CarrierTrack(12.5, 3.0, 2.2e7, 1.1e8, doppler) and type(made) is CarrierTrack
        assert dataclasses.asdict(made) == dataclasses.asdict(CarrierTrack(12.5, 3.0, 2.2e7, 1.1e8, doppler))
        with pytest.raises(dataclasses.FrozenInstanceError):
            made.count = 4.0  # type: ignore[misc]

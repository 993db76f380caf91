"""A recorded epoch becomes what a client would send: the API's bounds decide what is kept."""

from __future__ import annotations

import math

import numpy as np
from edgepos.gnss.rinex_obs import ObservationEpoch
from edgepos.pipelines.gnss_recording import epoch_pseudoranges

NAN = math.nan


def _epoch() -> ObservationEpoch:
    return ObservationEpoch(
        gpst=2300 * 604800.0 + 1234.5,
        flag=0,
        line_number=1,
        systems=("G", "G", "C", "E", "G"),
        prns=np.array([1, 2, 7, 11, 30]),
        pseudorange_m=np.array([2.1e7, NAN, 3.8e7, 2.4e7, 5.0e5]),
        cn0_dbhz=np.array([45.0, 40.0, NAN, 38.0, 30.0]),
        doppler_hz=np.array([-1200.5, 10.0, 25000.0, NAN, 0.0]),
        carrier_cycles=np.array([1.1e8, 1.0e8, NAN, 1.2e8, 1.0e8]),
        lli=np.array([1, 0, 0, 2, 0]),
    )


def test_only_pseudoranges_the_api_accepts_are_kept_with_what_was_recorded():
    kept = epoch_pseudoranges(_epoch())
    assert [(o.system, o.prn) for o in kept] == [("G", 1), ("C", 7), ("E", 11)]  # NaN and 500 km dropped
    first, beidou, galileo = kept
    assert first.t == 1234.5 and first.pseudorange == 2.1e7 and first.cn0 == 45.0
    assert (first.doppler_hz, first.carrier_cycles, first.lli) == (-1200.5, 1.1e8, 1)
    assert beidou.cn0 == 0.0  # no C/N0 recorded
    assert beidou.doppler_hz is None  # 25 kHz is beyond any receiver's Doppler
    assert beidou.carrier_cycles is None and beidou.lli is None  # no phase, so no loss-of-lock flag
    assert galileo.doppler_hz is None and galileo.lli == 2


def test_doppler_and_carrier_can_be_left_out():
    kept = epoch_pseudoranges(_epoch(), doppler=False, carrier=False)
    assert all(o.doppler_hz is None and o.carrier_cycles is None and o.lli is None for o in kept)
    assert len(kept) == 3

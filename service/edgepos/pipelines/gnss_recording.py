"""A recorded RINEX observation epoch as the pseudoranges a client would send to ``gnss_tight``.

One conversion for everything that replays a recording through the pipeline (``edgepos eval gnss-rinex``,
the benchmarks, the tests on the real files), so that they all feed it what the API would accept: the
time of week as ``t``; only pseudoranges inside the API's bounds; C/N0 0 where the file has none; the
Doppler where recorded and plausible; the carrier phase and its loss-of-lock indicator where recorded and
in range, or neither when ``carrier`` is off."""

from __future__ import annotations

import math

from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.rinex_obs import ObservationEpoch
from edgepos.pipelines.gnss_options import MAX_CARRIER_CYCLES, MAX_DOPPLER_HZ, SECONDS_PER_WEEK

MIN_PSEUDORANGE_M = 1.0e6
MAX_PSEUDORANGE_M = 1.0e8
"""The pseudoranges kept: GNSS satellites are 19,000-40,000 km away; a value outside is a receiver's
placeholder, not a measurement."""


def epoch_pseudoranges(
    epoch: ObservationEpoch, *, doppler: bool = True, carrier: bool = True
) -> list[PseudorangeObservation]:
    """The epoch's satellites as pseudorange observations (``doppler``/``carrier`` False leave those out)."""
    tow = epoch.gpst % SECONDS_PER_WEEK
    out = []
    for system, prn, pseudorange, cn0, doppler_hz, cycles, lli in zip(
        epoch.systems,
        epoch.prns,
        epoch.pseudorange_m,
        epoch.cn0_dbhz,
        epoch.doppler_hz,
        epoch.carrier_cycles,
        epoch.lli,
    ):
        if not (math.isfinite(pseudorange) and MIN_PSEUDORANGE_M <= pseudorange <= MAX_PSEUDORANGE_M):
            continue
        has_doppler = doppler and math.isfinite(doppler_hz) and abs(doppler_hz) <= MAX_DOPPLER_HZ
        has_carrier = carrier and math.isfinite(cycles) and abs(cycles) < MAX_CARRIER_CYCLES
        out.append(
            PseudorangeObservation(
                tow,
                system,
                int(prn),
                float(pseudorange),
                float(cn0) if math.isfinite(cn0) else 0.0,
                doppler_hz=float(doppler_hz) if has_doppler else None,
                carrier_cycles=float(cycles) if has_carrier else None,
                lli=int(lli) if has_carrier else None,
            )
        )
    return out

"""A loaded navigation file as the pipelines use it: broadcast orbits, Klobuchar set, summary, and the GPS
week that a time of week belongs to.

The service stores the RINEX text (``PUT /v1/ephemerides``) and every worker parses it into this object
(cached by content digest), so a pipeline only sees :class:`Ephemerides`.
"""

from __future__ import annotations

import functools
import hashlib
from collections import Counter
from dataclasses import dataclass

from edgepos.gnss.measurements import Atmosphere
from edgepos.gnss.orbits import MAX_AGE_S, BroadcastOrbits
from edgepos.gnss.rinex_nav import NavigationData, parse_navigation
from edgepos.gnss.timesys import SECONDS_PER_WEEK

DEFAULT_SIGNAL = {"G": "C1C", "C": "C2I", "E": "C1C"}
"""The pseudorange code assumed per system when the service computes satellite clocks (group delays) and
ionosphere scaling: GPS L1 C/A, BeiDou B1I, Galileo E1."""


@dataclass(frozen=True)
class Ephemerides:
    """Parsed broadcast ephemerides plus what the pipelines derive from them."""

    navigation: NavigationData
    orbits: BroadcastOrbits
    digest: str

    @classmethod
    def from_navigation(cls, navigation: NavigationData, digest: str = "") -> Ephemerides:
        return cls(navigation, BroadcastOrbits(navigation.ephemerides), digest)

    @property
    def atmosphere(self) -> Atmosphere:
        return Atmosphere.from_navigation(self.navigation)

    def validity(self) -> tuple[float, float] | None:
        """(first, last) GPS second at which some healthy ephemeris is valid; None without any."""
        return self._validity

    @functools.cached_property
    def _validity(self) -> tuple[float, float] | None:
        """:meth:`validity`, computed once: ``gpst`` asks for it at every epoch of every session."""
        usable = self.orbits.ephemerides
        if not usable:
            return None
        starts, ends = [], []
        for e in usable:
            age = MAX_AGE_S[e.system]
            half = e.fit_interval_s / 2.0 if age is None else age
            starts.append(e.toe - half)
            ends.append(e.toe + half)
        return float(min(starts)), float(max(ends))

    def gpst(self, time_of_week: float) -> float:
        """Continuous GPS seconds for a time of week: the week that puts it nearest the ephemerides' middle."""
        window = self.validity()
        if window is None:
            return time_of_week
        middle = 0.5 * (window[0] + window[1])
        week = round((middle - time_of_week) / SECONDS_PER_WEEK)  # half to even, as np.round: the same
        return float(week * SECONDS_PER_WEEK + time_of_week)

    def satellites(self) -> list[str]:
        return sorted({e.sat for e in self.orbits.ephemerides})

    def summary(self) -> dict[str, object]:
        """Counts by system, the satellites, the validity window and the header's ionosphere sets."""
        window = self.validity()
        return {
            "digest": self.digest,
            "records": dict(Counter(e.system for e in self.navigation.ephemerides)),
            "healthy_records": len(self.orbits),
            "skipped_records": dict(self.navigation.skipped),
            "satellites": self.satellites(),
            "valid_from_gpst": None if window is None else window[0],
            "valid_until_gpst": None if window is None else window[1],
            "ionosphere": sorted(self.navigation.ionosphere),
        }


def digest_of(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


@functools.lru_cache(maxsize=8)
def parse_ephemerides(text: str) -> Ephemerides:
    """Parse RINEX 3 navigation text (raises ``RinexError`` naming the line and field); cached by content."""
    return Ephemerides.from_navigation(parse_navigation(text.splitlines()), digest_of(text))

"""Fuzzy adaptation of pseudorange noise from elevation and C/N0 (Jiang & Chen 2018, Table 1, eq. 20).

Inputs: elevation (Low / Mid / High) and C/N0 (Small / Large); output: the precision class Good / Normal /
Bad, each a singleton scale factor mu on the pseudorange standard deviation R0 (eq. 20: sigma_i = mu_i R0).
Rules (Table 1): Large C/N0 with High elevation -> Good; Large with Mid or Low -> Normal; Small with High or
Mid -> Normal; Small with Low -> Bad. Inference: min for AND, weighted mean of the output singletons
(zero-order Sugeno defuzzification). The paper's figure of the membership functions is not in the text;
the breakpoints below are this project's choice and are parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ELEVATION_SETS = ("low", "mid", "high")
CN0_SETS = ("small", "large")
RULES: dict[tuple[str, str], str] = {
    ("large", "high"): "good",
    ("large", "mid"): "normal",
    ("large", "low"): "normal",
    ("small", "high"): "normal",
    ("small", "mid"): "normal",
    ("small", "low"): "bad",
}
"""Table 1: (C/N0 set, elevation set) -> precision class."""


def _ramp(x: np.ndarray, start: float, end: float) -> np.ndarray:
    """0 below ``start``, 1 above ``end``, linear between."""
    return np.clip((x - start) / (end - start), 0.0, 1.0)


@dataclass(frozen=True)
class FuzzyNoise:
    """Membership breakpoints (elevation in radians, C/N0 in dB-Hz) and the output singletons."""

    elevation_low_rad: float = np.deg2rad(15.0)
    """Fully Low below this; Mid rises from here."""
    elevation_mid_rad: float = np.deg2rad(35.0)
    """Peak of Mid; Low has fallen to 0 and High starts rising here."""
    elevation_high_rad: float = np.deg2rad(60.0)
    """Fully High above this; Mid has fallen to 0."""
    cn0_small_dbhz: float = 30.0
    """Fully Small below this."""
    cn0_large_dbhz: float = 45.0
    """Fully Large above this."""
    good: float = 1.0
    normal: float = 2.0
    bad: float = 4.0

    def memberships(
        self, elevation: np.ndarray, cn0: np.ndarray
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Degrees of membership of each input in its sets."""
        el = np.asarray(elevation, float)
        c = np.asarray(cn0, float)
        low = 1.0 - _ramp(el, self.elevation_low_rad, self.elevation_mid_rad)
        high = _ramp(el, self.elevation_mid_rad, self.elevation_high_rad)
        mid = np.minimum(
            _ramp(el, self.elevation_low_rad, self.elevation_mid_rad),
            1.0 - _ramp(el, self.elevation_mid_rad, self.elevation_high_rad),
        )
        large = _ramp(c, self.cn0_small_dbhz, self.cn0_large_dbhz)
        return {"low": low, "mid": mid, "high": high}, {"small": 1.0 - large, "large": large}

    def factor(self, elevation: np.ndarray, cn0: np.ndarray) -> np.ndarray:
        """mu per satellite: the scale of R0 (>= ``good``, <= ``bad``)."""
        elevation_degrees, cn0_degrees = self.memberships(elevation, cn0)
        singleton = {"good": self.good, "normal": self.normal, "bad": self.bad}
        numerator = np.zeros(np.broadcast(np.asarray(elevation), np.asarray(cn0)).shape)
        denominator = np.zeros_like(numerator)
        for (cn0_set, elevation_set), output in RULES.items():
            strength = np.minimum(cn0_degrees[cn0_set], elevation_degrees[elevation_set])
            numerator = numerator + strength * singleton[output]
            denominator = denominator + strength
        return numerator / np.maximum(denominator, 1e-12)

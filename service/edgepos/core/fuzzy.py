"""Fuzzy adaptation of pseudorange noise from elevation and C/N0 (Jiang & Chen 2018, Table 1, eq. 20).

Inputs: elevation (Low / Mid / High) and C/N0 (Small / Large); output: the precision class Good / Normal /
Bad, each a singleton scale factor mu on the pseudorange standard deviation R0 (eq. 20: sigma_i = mu_i R0).
Rules (Table 1): Large C/N0 with High elevation -> Good; Large with Mid or Low -> Normal; Small with High or
Mid -> Normal; Small with Low -> Bad. Inference: min for AND, weighted mean of the output singletons
(zero-order Sugeno defuzzification). The paper's figure of the membership functions is not in the text;
the breakpoints below are this project's choice and are parameters.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.measurements.gnss_noise_kernel import fuzzy_factor_kernel

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
        """mu per satellite: the scale of R0 (>= ``good``, <= ``bad``). One-dimensional inputs of one length
        go through the compiled loop (``gnss_noise_kernel.fuzzy_factor_kernel``: the same bits, some thirty
        numpy calls fewer) unless ``EDGEPOS_NUMBA=0`` or a value is not finite; the numpy form here is its
        reference."""
        el, c = np.asarray(elevation), np.asarray(cn0)
        if el.ndim == 1 and c.shape == el.shape and compiled_enabled():
            out = np.empty(el.shape)
            breakpoints, rules, outputs = _tables(self)
            if fuzzy_factor_kernel(
                np.ascontiguousarray(el, dtype=float),
                np.ascontiguousarray(c, dtype=float),
                breakpoints,
                rules,
                outputs,
                out,
            ):
                return out
        return self.numpy_factor(elevation, cn0)

    def numpy_factor(self, elevation: np.ndarray, cn0: np.ndarray) -> np.ndarray:
        """:meth:`factor` in numpy (the compiled loop's reference)."""
        elevation_degrees, cn0_degrees = self.memberships(elevation, cn0)
        singleton = {"good": self.good, "normal": self.normal, "bad": self.bad}
        numerator = np.zeros(np.broadcast(np.asarray(elevation), np.asarray(cn0)).shape)
        denominator = np.zeros_like(numerator)
        for (cn0_set, elevation_set), output in RULES.items():
            strength = np.minimum(cn0_degrees[cn0_set], elevation_degrees[elevation_set])
            numerator = numerator + strength * singleton[output]
            denominator = denominator + strength
        return numerator / np.maximum(denominator, 1e-12)


@functools.lru_cache(maxsize=16)
def _tables(noise: FuzzyNoise) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's breakpoints, rules (C/N0 set, elevation set) and singletons, in ``RULES``' order, built
    once per set of breakpoints (shared: nothing writes to them)."""
    singleton = {"good": noise.good, "normal": noise.normal, "bad": noise.bad}
    breakpoints = np.array(
        [
            noise.elevation_low_rad,
            noise.elevation_mid_rad,
            noise.elevation_high_rad,
            noise.cn0_small_dbhz,
            noise.cn0_large_dbhz,
        ],
        dtype=float,
    )
    rules = np.array(
        [[CN0_SETS.index(c), ELEVATION_SETS.index(e)] for c, e in RULES], dtype=np.int64
    ).reshape(len(RULES), 2)
    outputs = np.array([singleton[output] for output in RULES.values()], dtype=float)
    return breakpoints, rules, outputs  # writable: the kernel's one signature (it only reads them)

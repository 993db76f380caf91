"""gnss_tight's time-correlated error and noise level options on the wire (issue 21): out of bounds they
are 422s naming the option; on the real recording the correlation model reports a larger position
covariance than the white model for the same fixes, and the adaptive noise level never a smaller one."""

from __future__ import annotations

import pytest
from gnsswire import QUICK, assert_option_refused, quick_fixes, upload_ephemerides


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"error_correlation": "pink"}, "options.error_correlation"),
        ({"code_error_tau_s": 0.0}, "options.code_error_tau_s"),
        ({"code_error_tau_s": 1e5}, "options.code_error_tau_s"),
        ({"code_error_correlated_fraction": 1.5}, "options.code_error_correlated_fraction"),
        ({"code_error_correlated_fraction": -0.1}, "options.code_error_correlated_fraction"),
        ({"noise_level": "fixed"}, "options.noise_level"),
        ({"noise_level_time_constant_s": 5.0}, "options.noise_level_time_constant_s"),
        ({"noise_level_time_constant_s": 1e5}, "options.noise_level_time_constant_s"),
        ({"noise_level_reference": 0.0}, "options.noise_level_reference"),
        ({"noise_level_reference": 1e3}, "options.noise_level_reference"),
        ({"noise_level_reference_corrected": 0.0}, "options.noise_level_reference_corrected"),
        ({"noise_level_reference_corrected": 1e3}, "options.noise_level_reference_corrected"),
        ({"noise_level_reference_corrected": "low"}, "options.noise_level_reference_corrected"),
    ],
)
def test_correlation_options_out_of_bounds_are_422_naming_the_option(client, options, field):
    assert_option_refused(client, options, field)


def test_the_default_covariance_counts_correlated_errors(client):
    upload_ephemerides(client)
    fixed = {**QUICK, "noise_level": "model"}  # the correlation factor alone
    honest = quick_fixes(client, "car-1", fixed)
    white = quick_fixes(client, "car-2", {**fixed, "error_correlation": "white"})
    assert [(f["x"], f["y"]) for f in honest] == [(f["x"], f["y"]) for f in white]
    ratios = [
        h["position_covariance"][0][0] / w["position_covariance"][0][0] for h, w in zip(honest[2:], white[2:])
    ]
    assert all(r > 1.0 for r in ratios), ratios
    # the adaptive noise level (the default) only ever raises it, for the same fixes
    adaptive = quick_fixes(client, "car-3", QUICK)
    assert [(f["x"], f["y"]) for f in adaptive] == [(f["x"], f["y"]) for f in honest]
    assert all(
        a["position_covariance"][0][0] >= h["position_covariance"][0][0] for a, h in zip(adaptive, honest)
    )

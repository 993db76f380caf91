"""The parameters a client may set on motion models and filters: names, types and bounds checked with the
offending parameter named; and the GNSS motion models' process noise positive semidefinite over their
whole option range."""

from __future__ import annotations

import math

import numpy as np
import pytest
from edgepos.core.errors import ConfigurationError
from edgepos.core.filters import FILTERS, make_filter
from edgepos.core.motion import MOTION_MODELS, make_motion_model
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel, RissInput, RissModel
from edgepos.core.parameters import ParameterSpec, check_parameters


@pytest.mark.parametrize(
    ("params", "parameter"),
    [
        ({"sigma": 1e200}, "sigma"),
        ({"sigma": 0.0}, "sigma"),
        ({"alpha": math.nan}, "alpha"),
        ({"alpha": "1"}, "alpha"),
        ({"alpha": True}, "alpha"),
        ({"alpha": None}, "alpha"),
        ({"tau": 1.0}, "tau"),
    ],
)
def test_bad_model_parameters_name_the_parameter(params: dict, parameter: str) -> None:
    with pytest.raises(ConfigurationError) as caught:
        make_motion_model("singer", **params)
    assert caught.value.parameter == parameter


def test_bounds_are_inclusive_and_values_become_floats() -> None:
    model = make_motion_model("singer", alpha=1e-4, sigma=100)
    assert (model.alpha, model.sigma) == (1e-4, 100.0)
    assert make_filter("ukf", alpha=1.0, beta=0.0, kappa=None).kappa is None
    with pytest.raises(ConfigurationError) as caught:
        make_filter("ckf", alpha=1.0)
    assert caught.value.parameter == "alpha"


@pytest.mark.parametrize("owner", sorted({**MOTION_MODELS, **FILTERS}))
def test_every_constructor_parameter_is_published_and_its_bounds_build(owner: str) -> None:
    """Every published parameter is a constructor argument, and both ends of every range build."""
    cls = MOTION_MODELS.get(owner) or FILTERS[owner]
    make = make_motion_model if owner in MOTION_MODELS else make_filter
    for spec in cls.parameters:
        values = spec.choices if spec.choices is not None else (spec.minimum, spec.maximum)
        assert spec.minimum is None or spec.minimum <= spec.maximum
        for value in values:
            make(owner, **{spec.name: value})


def test_check_parameters_refuses_a_non_object() -> None:
    with pytest.raises(ConfigurationError):
        check_parameters(
            "x", (ParameterSpec("a", "a number", 0.0, 1.0),), [("a", 1.0)]
        )  # deliberately the wrong type


ANCHOR = GeodeticAnchor(math.radians(22.3), math.radians(114.2), 10.0)


@pytest.mark.parametrize("dt", [0.01, 1.0, 30.0])
@pytest.mark.parametrize("bias_psd", [1e-6, 1e-2, 1.0, 1e6])
@pytest.mark.parametrize("drift_psd", [1e-8, 0.1, 1e6])
def test_clock_process_noise_is_positive_semidefinite(dt: float, bias_psd: float, drift_psd: float) -> None:
    """Three constellation clocks integrate one drift: without the drift's common share in their cross
    covariances the noise was indefinite whenever bias_psd < 5/12 drift_psd dt^2 (gnss_tight's particle
    filters then refused every batch with clock_bias_psd below about 0.04, the drift at its default)."""
    models = [
        GnssOnlyModel(ANCHOR, clock_bias_psd=bias_psd, clock_drift_psd=drift_psd),
        RissModel(
            ANCHOR, RissInput(5.0, 0.0, 0.0, 0.01, 0.1), clock_bias_psd=bias_psd, clock_drift_psd=drift_psd
        ),
    ]
    for model in models:
        noise = model.process_noise(dt)
        eigenvalues = np.linalg.eigvalsh(noise)
        assert eigenvalues.min() >= -1e-12 * eigenvalues.max()
        np.linalg.cholesky(noise + 1e-12 * eigenvalues.max() * np.eye(len(noise)))

"""Options the two cooperative pipelines (``v2v_coop``, ``v2x_federated``) share: the GNSS fix error's
time-correlated part and how a neighbour's published estimate enters a range update."""

from __future__ import annotations

from edgepos.pipelines.base import OptionSpec

NEIGHBOUR_FUSION = ("intersection", "independent")
GNSS_BIAS_TAU = 35.0
"""s: the fix errors' autocorrelation on the real drive of tests/data/gnss-rover (docs/v2v.md)."""
GNSS_BIAS_STD = 2.1
"""m per axis: the same recording's fix errors less their white part (docs/v2v.md)."""
#: What a session created before these options existed did: white fixes, neighbours as independent.
LEGACY_OPTIONS = {"gnss_bias_tau": GNSS_BIAS_TAU, "gnss_bias_std": 0.0, "neighbour_fusion": "independent"}

GNSS_BIAS_SPECS = (
    OptionSpec(
        "gnss_bias_tau",
        "number",
        GNSS_BIAS_TAU,
        "Time constant (s) of the GNSS fix error's Gauss-Markov part (site x and y alike); measured on a "
        "real drive, docs/v2v.md.",
        minimum=0.1,
        maximum=3600.0,
    ),
    OptionSpec(
        "gnss_bias_std",
        "number",
        GNSS_BIAS_STD,
        "Stationary 1-sigma per axis (m) of the GNSS fix error's Gauss-Markov part, estimated as a state; "
        "0: fix errors white (independent from fix to fix).",
        minimum=0.0,
        maximum=1e3,
    ),
)


def neighbour_specs(fusion_description: str) -> tuple[OptionSpec, ...]:
    """``neighbour_fusion`` (described as the pipeline uses it), ``max_neighbour_age`` and
    ``neighbour_accel_std``."""
    return (
        OptionSpec(
            "neighbour_fusion", "string", "intersection", fusion_description, choices=NEIGHBOUR_FUSION
        ),
        OptionSpec(
            "max_neighbour_age",
            "number",
            1.0,
            "Oldest usable neighbour estimate (s) past its last point.",
            minimum=0.0,
            maximum=60.0,
        ),
        OptionSpec(
            "neighbour_accel_std",
            "number",
            1.0,
            "White acceleration (m/s^2) for predicting a neighbour forward.",
            minimum=0.0,
            maximum=100.0,
        ),
    )


CONSISTENCY_TIME_CONSTANT_S = 20.0
"""s: the consistency scale's memory (docs/integrity.md, "The fix's consistency scale": chosen on seeds 0
and 1 of the papers' scenes between 5 and 40 s)."""
CONSISTENCY_RISK_SHARE = 0.25
"""The share of the integrity risk the scale's upper bound spends: half of the fault-free half (the
protection level gives half the risk to the fault-free solution, half to the fault hypotheses; a scale
larger than its bound is a fault-free failure, as likely a priori as the error leaving its radius)."""
#: What a session stored before the consistency scale (or its bound) existed goes on with: its covariance
#: and protection level as reported then.
LEGACY_CONSISTENCY = {
    "consistency_scale": False,
    "consistency_time_constant_s": CONSISTENCY_TIME_CONSTANT_S,
    "consistency_bound": False,
    "consistency_risk_share": CONSISTENCY_RISK_SHARE,
}


def consistency_specs(default: bool, what: str) -> tuple[OptionSpec, ...]:
    """``consistency_scale`` (on by ``default``; ``what`` says which estimate it scales) and its memory."""
    return (
        OptionSpec(
            "consistency_scale",
            "boolean",
            default,
            "Multiply the fix's reported position covariance (and the protection level built on it) by the "
            "filter's own consistency scale: how much larger the GNSS fix innovations are than the predicted "
            f"covariance and the fix's noise explain, never below 1 ({what}). The estimate and its gains are "
            "unchanged, so the fix's position is the same either way (docs/integrity.md, \"The fix's "
            'consistency scale").',
        ),
        OptionSpec(
            "consistency_time_constant_s",
            "number",
            CONSISTENCY_TIME_CONSTANT_S,
            "Memory (s) of the consistency scale: each GNSS fix innovation's weight decays as exp(-age / this).",
            minimum=1.0,
            maximum=3600.0,
        ),
        OptionSpec(
            "consistency_bound",
            "boolean",
            True,
            "With consistency_scale: the protection level's error bounds use an upper confidence bound of the "
            "scale (estimated from little information, it may be larger than its estimate) rather than the "
            "estimate, which the reported covariance keeps; the fix is unavailable until its GNSS fixes bound "
            'the scale (docs/integrity.md, "The scale\'s upper bound").',
        ),
        OptionSpec(
            "consistency_risk_share",
            "number",
            CONSISTENCY_RISK_SHARE,
            "With consistency_bound: the share of integrity_risk allotted to the scale exceeding its upper "
            "bound (whose confidence is 1 - this x integrity_risk); the protection level is sized with the rest.",
            minimum=0.01,
            maximum=0.99,
        ),
    )

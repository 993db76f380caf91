"""The ``gnss_tight`` pipeline's options: their bounds and defaults, each with the reason for it (these
descriptions are the API docs of the session options), and the limits its input checks use."""

from __future__ import annotations

import math

from edgepos.core.particles import PARTICLE_FILTERS
from edgepos.gnss.carrier import (
    DEFAULT_CODE_JUMP_M,
    DEFAULT_MAX_GAP_S,
    DEFAULT_SLIP_CYCLES_PER_S,
    DEFAULT_WINDOW_S,
)
from edgepos.gnss.differential import DEFAULT_MAX_AGE_S, MAX_AGE_BOUNDS_S
from edgepos.gnss.error_correlation import FITTED_CORRELATION
from edgepos.gnss.measurements import DEFAULT_GALILEO_GROUP_DELAY, GALILEO_GROUP_DELAYS
from edgepos.gnss.tdcp import DEFAULT_PHASE_STD_M
from edgepos.pipelines.base import (
    OptionSpec,
)
from edgepos.pipelines.gnss_faults import (
    DEFAULT_FAULT_PERSISTENCE,
    DEFAULT_FAULT_PROBABILITY,
    DEFAULT_FAULT_RECOVERY,
)
from edgepos.pipelines.gnss_integrity import INTEGRITY_SPECS

NEAREST_BASE_STATION = "nearest"

SYSTEMS = ("G", "C", "E")
MAX_PRN = 63
SECONDS_PER_WEEK = 604800.0
MAX_CARRIER_CYCLES = 1.0e10
"""Largest |carrier phase| accepted (cycles): RINEX writes it as F14.3, below 1e10; float64 keeps 1e-6 cycle
there."""
MAX_LLI = 7
"""RINEX loss-of-lock indicators are three bits."""
CARRIER_SMOOTHING = ("hatch", "off", "tdcp", "hatch+tdcp")
DEFAULT_CARRIER_SMOOTHING = "hatch+tdcp"
DEFAULT_HATCH_STD_FLOOR = 0.2
ERROR_CORRELATIONS = ("gauss_markov", "white")
DEFAULT_ERROR_CORRELATION = "gauss_markov"
NOISE_LEVELS = ("adaptive", "model")
DEFAULT_NOISE_TIME_CONSTANT_S = 60.0
"""One correlation time of the errors (code_error_tau_s 56 s), six of the epoch estimates' own (about 10 s);
the reasoning and the first half's figures are in docs/gnss.md ("Following the noise level")."""
DEFAULT_NOISE_REFERENCE = 0.15
"""The estimate's level on the first half of tests/data/gnss-rover, raw code (0.152 with the UPF at the
defaults, ``python bench/gnss_noise_reference.py``)."""
DEFAULT_NOISE_REFERENCE_CORRECTED = 0.13
"""The same level of the rows with a differential correction from the recording's reference station, first
half, raw code (0.132 with the UPF: ``python bench/gnss_noise_reference.py --base``; 0.097, and 0.10 here,
before the Galileo group delay was settled: the station's and the vehicle's receivers now model their own,
docs/gnss.md)."""
MIXED_CORRECTIONS = ("exclude", "use")
DEFAULT_MIXED_CORRECTIONS = "exclude"
NOISE_MODELS = ("fuzzy", "fitted")
DEFAULT_NOISE_MODEL = "fitted"
DEFAULT_NHC = False
DEFAULT_NHC_LATERAL_ACCEL_STD = 1.0
DEFAULT_NHC_VERTICAL_STD_MPS = 0.3
DEFAULT_ZUPT = True
DEFAULT_ZUPT_SPEED_MPS = 0.3
DEFAULT_ZUPT_EPOCHS = 2
DEFAULT_ZUPT_STD_MPS = 0.05
MAX_DOPPLER_HZ = 20000.0
"""Largest |Doppler| accepted: a ground receiver sees at most about 5 kHz on L1 from satellite motion, plus
its oscillator's offset (a few kHz for a poor one)."""
DEFAULT_DOPPLER_STD_MPS = 0.25
DEFAULT_DOPPLER_OUTLIER_STD_MPS = 5.0
"""The Doppler options' defaults, also for sessions stored before the options existed (they sent no Doppler,
but a client of such a session may start to)."""
OPTION_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec(
        "filter",
        "string",
        "upf",
        "upf: the paper's unscented particle filter (a UKF proposal per particle); pf: bootstrap particle "
        "filter (prior as proposal); ukf: a single unscented Kalman filter (cheap baseline).",
        choices=tuple(PARTICLE_FILTERS),
    ),
    OptionSpec(
        "particles",
        "integer",
        200,
        "Particles of the pf and upf filters (ignored by ukf). The maximum bounds the session state, stored "
        "with every batch (about 290 kB at 700 particles with the default lag window); one epoch of the most "
        "pseudoranges accepted (40) then fits the default CPU budget per batch (EDGEPOS_BATCH_CPU_BUDGET_MS, "
        "50 ms) with either filter (the cost model allows about 1,700 pf or 28,000 upf particles there). A "
        "session whose options would not fit one such epoch in the server's budget (a smaller "
        "EDGEPOS_BATCH_CPU_BUDGET_MS) is refused with 422 saying how many fit.",
        10,
        700,
    ),
    OptionSpec(
        "resample_threshold",
        "number",
        0.5,
        "Resample when the effective sample size falls below this fraction of the particles.",
        0.0,
        1.0,
    ),
    OptionSpec(
        "spread_fraction",
        "number",
        0.02,
        "upf: the fraction of each particle's UKF proposal covariance the particles carry as their spread; "
        "each keeps the rest as its own covariance. 1: the particles alone carry the uncertainty; near 0: "
        "each particle is a UKF. 0.02 measured best on the simulated urban drive (docs/gnss-simulation.md).",
        0.0,
        1.0,
    ),
    OptionSpec(
        "fuzzy",
        "boolean",
        True,
        "Scale each pseudorange's noise by the fuzzy factor of its elevation and C/N0 (Table 1, eq. 20); "
        "off: every pseudorange has pseudorange_std.",
    ),
    OptionSpec(
        "pseudorange_std",
        "number",
        2.0,
        "R0: pseudorange noise std (m) before the fuzzy factor.",
        0.01,
        1000.0,
    ),
    OptionSpec(
        "outlier_probability",
        "number",
        0.1,
        "PF and UPF: each pseudorange's likelihood in the particle weights is the mixture (1 - p) N(0, "
        "(R0 x fuzzy factor)^2) + p N(0, outlier_std^2), a heavy tail for reflected (NLOS) signals and other "
        "errors the Gaussian does not model (the UPF's UKF proposal stays Gaussian). 0.1: one range in ten "
        "may be an outlier, a generic robust-likelihood prior (not fitted to a scenario). 0: Gaussian. Not "
        "used by the UKF.",
        0.0,
        0.9,
    ),
    OptionSpec(
        "outlier_std",
        "number",
        30.0,
        "Std (m) of the likelihood's outlier component (see outlier_probability): the size of a reflected "
        "signal's extra path in a street canyon, tens of metres.",
        0.1,
        10000.0,
    ),
    OptionSpec(
        "use_doppler",
        "boolean",
        True,
        "Use each pseudorange's doppler_hz as a range rate in the update (velocity and receiver clock drift) "
        "and in the least-squares initialisation; off: every Doppler is reported unused (to measure what "
        "Doppler adds).",
    ),
    OptionSpec(
        "doppler_std_mps",
        "number",
        DEFAULT_DOPPLER_STD_MPS,
        "Range-rate noise std (m/s) of a Doppler before the fuzzy factor (its pseudorange's factor when fuzzy "
        "is on). 0.25: the RMS (0.23 m/s) of the first half of tests/data/gnss-rover's Doppler residuals at "
        "the reference trajectory, each divided by its fuzzy factor, rounded up (docs/gnss.md).",
        0.001,
        100.0,
    ),
    OptionSpec(
        "doppler_outlier_std_mps",
        "number",
        DEFAULT_DOPPLER_OUTLIER_STD_MPS,
        "PF and UPF: std (m/s) of a Doppler likelihood's outlier component (see outlier_probability): a "
        "reflected signal's range rate differs from the direct one's by up to twice the vehicle's speed, "
        "metres per second in town.",
        0.01,
        1000.0,
    ),
    OptionSpec(
        "carrier_smoothing",
        "string",
        DEFAULT_CARRIER_SMOOTHING,
        "What a pseudorange's carrier_cycles is used for. hatch: carrier-smoothed code (Hatch filter per "
        "satellite, gnss/carrier.py): the smoothed pseudorange replaces the raw one in the update with its "
        "noise std scaled by max(1/sqrt(epochs averaged), hatch_std_floor) (the fix's covariance then counts "
        "the average's correlated errors: error_correlation); a cycle slip (lli bit 0, phase "
        "change against the integrated Doppler, code-carrier jump, a gap) restarts that satellite's average "
        "only. tdcp: time-differenced carrier phase (gnss/tdcp.py, pipelines/gnss_tdcp.py): the phases' "
        "changes since the previous epoch give the receiver's displacement to centimetres (least squares with "
        "a chi-square test that leaves out a slipped or reflected satellite's difference), which replaces the "
        "constant-velocity model's position step (GNSS-only model; the code is used raw). hatch+tdcp (the "
        "default): both; the best of the four on the first half of tests/data/gnss-rover for the UKF and the "
        "UPF, with and without the reference station (docs/gnss.md). "
        "off: carrier phase is ignored. Sessions stored before the option existed keep off.",
        choices=CARRIER_SMOOTHING,
    ),
    OptionSpec(
        "tdcp_phase_std_m",
        "number",
        DEFAULT_PHASE_STD_M,
        "tdcp: std (m) of a satellite's phase difference between epochs at zenith, divided by sin(elevation) "
        "(floored at 10 deg); the displacement's covariance is the filter's position process noise, so this "
        "also sets how many epochs of code the filter averages. Carrier noise is millimetres and multipath on "
        "the phase centimetres (at 0.02 the fits on the first half of tests/data/gnss-rover have a chi-square "
        "variance factor of 0.48); 0.05 was chosen on that half as the value within 2 % of the best RMS whose "
        "mean NEES is nearest 2 (0.02: a longer memory, whose correlated code errors the fix's covariance "
        "under-counts; docs/gnss.md).",
        0.001,
        1.0,
    ),
    OptionSpec(
        "hatch_window_s",
        "number",
        DEFAULT_WINDOW_S,
        "Hatch filter memory (s): the average weighs at most window / epoch interval epochs. 100 s (the SBAS "
        "standard's): on one frequency the smoothed code drifts by twice the ionosphere's change over the window, "
        "decimetres at 100 s, while code multipath averages down.",
        1.0,
        3600.0,
    ),
    OptionSpec(
        "hatch_std_floor",
        "number",
        DEFAULT_HATCH_STD_FLOOR,
        "Smallest fraction of the raw pseudorange std a smoothed pseudorange gets in the filter's update (the "
        "weights): averaging n epochs divides white noise by sqrt(n), but street-canyon multipath is "
        "correlated over tens of seconds. Chosen on the first half of tests/data/gnss-rover (docs/gnss.md). "
        "The covariance the fix reports does not rely on it (error_correlation): there a smoothed range's "
        "error is the average of correlated errors (std 0.59 of the raw code's after 100 epochs at the "
        "defaults, against this floor's 0.2).",
        0.01,
        1.0,
    ),
    OptionSpec(
        "error_correlation",
        "string",
        DEFAULT_ERROR_CORRELATION,
        "What the fix's covariance assumes about pseudorange errors over time. The filters weigh the "
        "pseudoranges as independent between epochs (white) either way, so the fixes are the same. "
        "gauss_markov: each error is a white part plus a first-order Gauss-Markov part (code_error_tau_s, "
        "code_error_correlated_fraction; gnss/error_correlation.py), and the position covariance the fix "
        "reports (and the prior the integrity monitor tests against) is the filter's times the factor by "
        "which the error of its weighted solution grows under that model (a consider covariance): a "
        "carrier-smoothed range's error is an average of correlated errors (not std/sqrt(n)), and the filter's "
        "memory (about 1 + the epoch's own least-squares horizontal variance over the predicted one, in "
        "epochs) averages correlated errors, which do not fall as 1/memory. Mean NEES (2 dof) of the UPF's "
        "fixes on tests/data/gnss-rover 3.6, not 25 (2.3 with noise_level adaptive; docs/gnss.md). With filter pf the reported horizontal "
        "covariance is also at least that factor times a Gaussian update's of the same prediction (a couple "
        "of hundred particles' covariance collapses on resampling). white: the filter's own covariance. "
        "Sessions stored before the option existed keep white.",
        choices=ERROR_CORRELATIONS,
    ),
    OptionSpec(
        "code_error_tau_s",
        "number",
        FITTED_CORRELATION.tau_s,
        "gauss_markov: correlation time (s) of the pseudorange error's correlated part (multipath, residual "
        "atmosphere and orbit errors). 56 s: fitted to the autocorrelation of the standardised pseudorange "
        "residuals at the reference trajectory of the first half of tests/data/gnss-rover (0.93 at 1 s, 0.48 "
        "at 10 s, 0.26 at 60 s; python -m edgepos.gnss.error_correlation, docs/gnss.md).",
        0.01,
        3600.0,
    ),
    OptionSpec(
        "code_error_correlated_fraction",
        "number",
        FITTED_CORRELATION.fraction,
        "gauss_markov: the fraction of a pseudorange's error variance that is correlated over "
        "code_error_tau_s (the rest is white). 0.57: the same fit. 0 makes the errors white.",
        0.0,
        1.0,
    ),
    OptionSpec(
        "noise_level",
        "string",
        "adaptive",
        "Whether the fix's covariance follows the pseudoranges' noise level of the moment. adaptive: each "
        "epoch's update rows are fitted by least squares on their own, their residuals standardised by the "
        "error variance the noise model and error_correlation give them (leverage-corrected, so the fit's "
        "lost degrees of freedom are counted), the median of their squares over its expectation is the "
        "epoch's variance scale (one reflected satellite cannot blow it up), and the epochs' scales are "
        "averaged with exponential memory (noise_level_time_constant_s, weights rows - unknowns); the "
        "position covariance the fix reports (and its protection level) is multiplied by that average over "
        "noise_level_reference when above 1, never reduced. The filters' weights and the fixes are the same either way. On the second "
        "half of tests/data/gnss-rover the errors are 2.4 times the first half's variance (docs/gnss.md). "
        "model: the noise model's level. Sessions stored before the option existed keep model.",
        choices=NOISE_LEVELS,
    ),
    OptionSpec(
        "noise_level_time_constant_s",
        "number",
        DEFAULT_NOISE_TIME_CONSTANT_S,
        "adaptive noise level: the time constant (s) of its exponential memory. The errors are correlated "
        "over about a minute (code_error_tau_s), so a shorter memory sees one error, not its spread; a longer "
        "one follows a changing street late. 60 s: one correlation time of the errors, about six of the "
        "epoch estimates' own (their autocorrelation is 0.19 at 10 s on the first half of "
        "tests/data/gnss-rover; docs/gnss.md).",
        10.0,
        3600.0,
    ),
    OptionSpec(
        "noise_level_reference",
        "number",
        DEFAULT_NOISE_REFERENCE,
        "adaptive noise level: the estimate's value where the noise model and error_correlation hold; the "
        "covariance is scaled by estimate / reference. Below 1 because the residuals after the epoch's own "
        "fit do not show the errors the fix absorbs (correlated between satellites) and the screens remove "
        "the heavy tail the noise model's mean-square fit includes. 0.15: the estimate's level on the first "
        "half of tests/data/gnss-rover, raw code, where the model was fitted (0.152; with the carrier 0.19).",
        0.001,
        100.0,
    ),
    OptionSpec(
        "noise_level_reference_corrected",
        "number",
        DEFAULT_NOISE_REFERENCE_CORRECTED,
        "adaptive noise level: noise_level_reference for the rows with a differential correction from the "
        "site's reference station (base_station), whose post-fit residuals are smaller than raw code's. Applied "
        "per row (a corrected row's variance times this over noise_level_reference), so an epoch mixing "
        "corrected and uncorrected rows gives one level whatever the mix. 0.13: the estimate's level of the "
        "corrected rows on the first half of tests/data/gnss-rover with its reference station, raw code "
        "(0.132; python bench/gnss_noise_reference.py --base, docs/gnss.md). No effect without corrections.",
        0.001,
        100.0,
    ),
    OptionSpec(
        "carrier_slip_cycles_per_s",
        "number",
        DEFAULT_SLIP_CYCLES_PER_S,
        "Cycle-slip test: restart a satellite's smoothing when its phase change differs from its integrated "
        "Doppler by more than this many cycles per second of interval (needs doppler_hz and use_doppler).",
        0.1,
        1.0e4,
    ),
    OptionSpec(
        "carrier_code_jump_m",
        "number",
        DEFAULT_CODE_JUMP_M,
        "Cycle-slip test: restart a satellite's smoothing when its code differs from the carrier-propagated "
        "smoothed range by more than this (m).",
        0.1,
        1.0e4,
    ),
    OptionSpec(
        "carrier_max_gap_s",
        "number",
        DEFAULT_MAX_GAP_S,
        "Longest time (s) between a satellite's carrier phases its smoothing continues across.",
        0.01,
        600.0,
    ),
    OptionSpec(
        "noise_model",
        "string",
        DEFAULT_NOISE_MODEL,
        "Pseudorange noise std before carrier smoothing. fuzzy: pseudorange_std x the fuzzy factor of "
        "elevation and C/N0 (Table 1, eq. 20; with fuzzy off, pseudorange_std alone). fitted: sqrt(a^2 + "
        "b^2/sin^2(el) + c^2 10^((45 - C/N0)/10)) with a, b, c fitted to the pseudorange residuals at the "
        "reference trajectory of the first half of tests/data/gnss-rover (gnss/pseudorange_noise.py, "
        "docs/gnss.md); pseudorange_std is then unused. A Doppler's std keeps the fuzzy factor either way.",
        choices=NOISE_MODELS,
    ),
    OptionSpec(
        "fault_probability",
        "number",
        DEFAULT_FAULT_PROBABILITY,
        "Faults caught over time (pipelines/gnss_faults.py): a pseudorange (or range rate) whose innovation "
        "against the filter's prediction exceeds this chi-square(1) quantile is suspect and down-weighted "
        "(std raised to put it on the gate); suspect for fault_persistence epochs in a row it is excluded "
        "until it agrees for fault_recovery epochs. 0 disables. The reason is in the fix's measurement list.",
        0.0,
        0.999999,
    ),
    OptionSpec(
        "fault_persistence",
        "integer",
        DEFAULT_FAULT_PERSISTENCE,
        "Epochs in a row a satellite's innovation must be suspect before it is excluded: reflected (NLOS) "
        "and multipath signals persist for seconds in a street canyon, noise does not.",
        1,
        100,
    ),
    OptionSpec(
        "fault_recovery",
        "integer",
        DEFAULT_FAULT_RECOVERY,
        "Epochs in a row an excluded satellite's innovation must agree with the prediction before it is "
        "used again.",
        1,
        100,
    ),
    OptionSpec(
        "nhc",
        "boolean",
        DEFAULT_NHC,
        "Non-holonomic constraint when a batch has no riss sample: the lateral and vertical velocity in the "
        "vehicle frame (heading = the predicted velocity's azimuth, above 1 m/s) are zero-valued "
        "pseudo-measurements; the fix lists it under constraints.",
    ),
    OptionSpec(
        "nhc_lateral_accel_std",
        "number",
        DEFAULT_NHC_LATERAL_ACCEL_STD,
        "NHC: lateral velocity std per second of epoch interval (m/s^2): the heading turns during the "
        "interval, so this is the lateral acceleration of a car in town relative to its previous heading.",
        0.01,
        100.0,
    ),
    OptionSpec(
        "nhc_vertical_std_mps",
        "number",
        DEFAULT_NHC_VERTICAL_STD_MPS,
        "NHC: vertical velocity std (m/s), for road grades (5 % at 10 m/s is 0.5 m/s).",
        0.01,
        100.0,
    ),
    OptionSpec(
        "zupt",
        "boolean",
        DEFAULT_ZUPT,
        "Zero-velocity update when a batch has no riss sample: when the epoch's own Doppler least-squares "
        "velocity has been below zupt_speed_mps for zupt_epochs epochs in a row, the velocity is a zero-valued "
        "pseudo-measurement (std zupt_std_mps); the fix lists it under constraints.",
    ),
    OptionSpec(
        "zupt_speed_mps",
        "number",
        DEFAULT_ZUPT_SPEED_MPS,
        "ZUPT: horizontal Doppler speed (m/s) below which an epoch counts as standing still; above the "
        "Doppler velocity's noise (about 0.1-0.3 m/s here), below a car's creeping speed.",
        0.01,
        5.0,
    ),
    OptionSpec(
        "zupt_epochs",
        "integer",
        DEFAULT_ZUPT_EPOCHS,
        "ZUPT: epochs in a row the Doppler speed must stay below zupt_speed_mps.",
        1,
        100,
    ),
    OptionSpec(
        "zupt_std_mps",
        "number",
        DEFAULT_ZUPT_STD_MPS,
        "ZUPT: velocity std (m/s) of the zero-velocity pseudo-measurement (engine vibration, a creeping car).",
        0.001,
        10.0,
    ),
    OptionSpec(
        "systems",
        "string[]",
        list(SYSTEMS),
        "Constellations used (RINEX letters G GPS, C BeiDou, E Galileo); others are reported unused.",
        choices=SYSTEMS,
    ),
    OptionSpec("elevation_mask", "number", math.radians(10.0), "Elevation mask (rad).", -0.1, 1.5),
    OptionSpec("min_cn0", "number", 0.0, "Pseudoranges below this C/N0 (dB-Hz) are not used.", 0.0, 80.0),
    OptionSpec(
        "gate_probability",
        "number",
        0.9999,
        "Residual test: exclude a pseudorange (or a Doppler's range rate) whose normalised residual squared "
        "exceeds this chi-square(1) quantile; 0 disables.",
        0.0,
        0.999999999,
    ),
    OptionSpec(
        "fde_probability",
        "number",
        0.999,
        "Snapshot fault detection and exclusion, as in the least-squares baseline: while the chi-square test "
        "(this level) of the epoch's weighted least-squares residuals, linearised at the prediction, fails, "
        "the pseudorange with the largest standardised residual is excluded; 0 disables.",
        0.0,
        0.999999999,
    ),
    OptionSpec(
        "max_exclusions", "integer", 4, "Pseudoranges the snapshot test may exclude per epoch.", 0, 30
    ),
    OptionSpec(
        "ionosphere", "boolean", True, "Apply the broadcast Klobuchar ionosphere (needs ephemerides)."
    ),
    OptionSpec("troposphere", "boolean", True, "Apply the Saastamoinen troposphere."),
    OptionSpec(
        "accel_std",
        "number",
        3.0,
        "GNSS-only model: horizontal white-noise acceleration (m/s^2); a car braking, accelerating and "
        "cornering in town reaches 2-4 m/s^2.",
        1e-3,
        100.0,
    ),
    OptionSpec(
        "vertical_accel_std",
        "number",
        0.3,
        "GNSS-only model: vertical white-noise acceleration (m/s^2).",
        1e-3,
        100.0,
    ),
    OptionSpec("wheel_speed_std", "number", 0.1, "RISS model: wheel speed noise (m/s).", 1e-4, 10.0),
    OptionSpec("accelerometer_std", "number", 0.05, "RISS model: accelerometer noise (m/s^2).", 1e-4, 10.0),
    OptionSpec("gyro_std", "number", 0.005, "RISS model: yaw gyro noise (rad/s).", 1e-6, 1.0),
    OptionSpec(
        "gyro_bias_std",
        "number",
        0.002,
        "RISS model: initial std of the yaw gyro's bias (rad/s; 0.002 = 0.11 deg/s, a MEMS gyro's turn-on "
        "bias after start-up calibration), estimated in the state.",
        1e-6,
        0.1,
    ),
    OptionSpec(
        "gyro_bias_psd",
        "number",
        1e-10,
        "RISS model: random-walk density of the gyro bias (rad^2/s^3; 1e-10 lets it wander 0.03 deg/s in "
        "an hour, the bias instability of a 10 deg/h MEMS gyro).",
        0.0,
        1e-4,
    ),
    OptionSpec(
        "wheel_scale_std",
        "number",
        0.01,
        "RISS model: initial std of the wheel speed's scale error (0.01: a tyre's rolling radius known to "
        "1 %), estimated in the state.",
        1e-6,
        0.2,
    ),
    OptionSpec(
        "clock_bias_psd", "number", 1.0, "Receiver clock bias random-walk density (m^2/s).", 1e-6, 1e6
    ),
    OptionSpec(
        "clock_drift_psd", "number", 0.1, "Receiver clock drift random-walk density (m^2/s^3).", 1e-8, 1e6
    ),
    OptionSpec(
        "riss_timeout",
        "number",
        1.5,
        "Use the RISS model while the last riss sample is at most this old (s); otherwise GNSS-only.",
        0.01,
        60.0,
    ),
    OptionSpec(
        "max_gap",
        "number",
        30.0,
        "Longest time (s) between epochs the filter predicts across; after a longer gap it starts again "
        "from the next least-squares fix.",
        0.1,
        86400.0,
    ),
    OptionSpec(
        "init_velocity_std", "number", 10.0, "Velocity std (m/s) when initialising from a fix.", 0.01, 1000.0
    ),
    OptionSpec(
        "base_station",
        "string",
        None,
        "Differential corrections from a reference station registered with POST /v1/base-stations: its id, "
        "or 'nearest' (the registered station with a position nearest the session's last fix, else the site "
        "origin). Each pseudorange gets the correction of the newest base epoch at or before its epoch, "
        "within max_correction_age_s and computed with the same broadcast ephemeris (IODE and toe); each "
        "pseudorange of a fix reports correction_applied and correction_reason. null: no corrections.",
    ),
    OptionSpec(
        "max_correction_age_s",
        "number",
        DEFAULT_MAX_AGE_S,
        "With base_station: a correction older than this (s, rover epoch minus base epoch) is not applied "
        "and the pseudorange says so. 30 s: a held correction changes by 0.21 m RMS in 30 s on "
        "tests/data/gnss-rover, below the corrected pseudoranges' noise (docs/gnss.md).",
        MAX_AGE_BOUNDS_S[0],
        MAX_AGE_BOUNDS_S[1],
    ),
    OptionSpec(
        "correction_systems",
        "string[]",
        list(SYSTEMS),
        "With base_station: the constellations whose pseudoranges take the station's corrections (RINEX "
        "letters); the others are used uncorrected and say so. A code correction carries the base "
        "receiver's own biases, which the rover's may not share: on tests/data/gnss-rover the station's "
        "Galileo corrections were off by up to 3 m per satellite from what the rover's receiver sees until "
        "the two receivers' Galileo group delays were told apart (galileo_group_delay); leaving Galileo "
        "uncorrected then measured 1.67 against 1.81 m on the first half, 2.44 against 2.30 m on the second "
        "(docs/gnss.md). All by default.",
        choices=SYSTEMS,
    ),
    OptionSpec(
        "galileo_group_delay",
        "string",
        DEFAULT_GALILEO_GROUP_DELAY,
        "What the vehicle receiver's Galileo E1 code carries of the satellite's group delay, when the service "
        "computes the satellites' clocks from the ephemerides. broadcast: the Galileo ICD's model, the clock "
        "less the BGD of the record's clock pair (E1/E5b for I/NAV, E1/E5a for F/NAV records); none: the clock "
        "without it. Receivers differ (python -m edgepos.gnss.group_delay_check measures one at known "
        "positions): on tests/data/gnss-rover the vehicle's Septentrio mosaic-X5 fits none (slope -0.11 +- "
        "0.17 on the first half), the reference station's Leica GR50 broadcast (0.56 +- 0.36; with the "
        "vehicle at none the differential fixes are 2.07 m with the station at broadcast, 2.77 m at none). "
        "none: chosen on the first half of the recording "
        "(horizontal RMS, UPF with the carrier: 2.12 -> 1.93 m, with the station 2.14 -> 1.81 m; the second "
        "half 3.35 -> 2.58 m and 3.26 -> 2.29 m; docs/gnss.md). Set broadcast for a receiver that follows the "
        "ICD. A reference station has its own (POST /v1/base-stations, broadcast by default). Sessions stored before the option "
        "keep broadcast.",
        choices=GALILEO_GROUP_DELAYS,
    ),
    OptionSpec(
        "mixed_corrections",
        "string",
        DEFAULT_MIXED_CORRECTIONS,
        "With differential corrections: what to do with a pseudorange that has none (a satellite the base "
        "does not track or sees below its mask, a stale correction) when at least two satellites of its "
        "constellation have one. A correction is relative to the base's median model error per "
        "constellation, so the corrected satellites' clock is offset from an uncorrected one's by that "
        "satellite's own orbit, clock and atmosphere model error (2.0 m median for BeiDou C36 on "
        "tests/data/gnss-rover). exclude: leave it out, the same as giving it its own clock (its Doppler is "
        "still used); use: use it with the others' clock. Chosen on the first half of the recording (horizontal "
        "RMS with the carrier: UPF 2.16 -> 2.13 m, UKF 2.15 -> 2.13 m, PF 2.13 -> 2.09 m); on the second half "
        "the UPF and UKF lose 3 cm, the PF gains 6 cm (docs/gnss.md). Sessions stored before the option "
        "keep use.",
        choices=MIXED_CORRECTIONS,
    ),
    OptionSpec(
        "gps_week", "integer", None, "GPS week of the times of week when no ephemerides are loaded.", 0, 10000
    ),
    OptionSpec(
        "seed",
        "integer",
        None,
        "Random seed of the particle filters; null draws one at session creation (stored in the state, so "
        "a replay gives the same fixes).",
        0,
        2**63 - 1,
    ),
) + INTEGRITY_SPECS

"""The state a ``gnss_tight`` session keeps between batches (options, clocks seen, the RISS input, the
particle cloud or UKF moments) and its exact byte form. Split from ``gnss_tight``."""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from edgepos.core import state as state_format
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor
from edgepos.core.particles import PARTICLE_FILTERS, Cloud
from edgepos.gnss.carrier import CarrierTable
from edgepos.gnss.noise_level import NoiseLevel
from edgepos.gnss.tdcp import PhaseHistory

PIPELINE_NAME = "gnss_tight"


@dataclass
class GnssSession:
    """A gnss_tight session between batches."""

    options: dict[str, Any]
    seed: int
    initialised: bool
    t: float | None
    filter_t: float | None
    epochs: int
    anchor: GeodeticAnchor | None
    riss: dict[str, float] | None
    clock_seen: dict[str, float]
    cloud: Cloud
    """The filter's cloud. When its weighted moments are known (the UPF's step computes them for the cloud it
    returns, unless it resampled) they are stored beside it as ``moments_mean`` and ``moments_cov``, exactly
    ``Cloud.moments`` of the stored particles, so the next epoch does not compute them again."""
    heading_known: bool = False
    """Whether the RISS model may run: until the GNSS-only model's velocity gives the azimuth, the RISS
    input is held back (a wrong initial azimuth is not recoverable once the model integrates the gyro)."""
    carrier: CarrierTable = field(default_factory=CarrierTable)
    """Per satellite, its carrier smoothing (gnss.carrier), independent of the filter (kept across a
    re-initialisation). Stored as the ``carrier_sats`` list and the ``carrier`` array as they are; states
    written before carrier phase have neither and start with none."""
    faults: dict[str, list[float]] = field(default_factory=dict)
    """Per satellite (and ``<sat>/rate`` for its range rate), the fault test's history over time
    (pipelines/gnss_faults.py); states written before it start with none. Stored as the ``fault_keys`` list
    and the ``faults`` array (n, 4); states written before that layout have the dict in their metadata."""
    still_epochs: int = 0
    """Epochs in a row whose own Doppler speed was below ``zupt_speed_mps`` (zero-velocity detection)."""
    noise: NoiseLevel = field(default_factory=NoiseLevel)
    """The pseudoranges' running noise level (``noise_level`` adaptive, gnss/noise_level.py), kept across a
    re-initialisation. Stored as the ``noise_level`` list; states written before it have none: no history."""
    options_text: str | None = field(default=None, repr=False, compare=False)
    """The JSON text ``options`` was decoded from, written back as it is while the options equal its parse
    (``options_json``): encoding and parsing some seventy options took about a fifth of the state's time."""

    tdcp: PhaseHistory = field(default_factory=PhaseHistory)
    """The previous filter epoch's carrier phases for the next epoch's differences (``carrier_smoothing``
    tdcp, pipelines/gnss_tdcp.py). Stored as ``tdcp_head`` ([t, x, y, z]) and ``tdcp_sats`` and the ``tdcp``
    array, only when it holds phases; states written without them start with none."""

    def to_bytes(self) -> bytes:
        text = self.options_text
        if text is None or _parsed_options(text) != self.options:
            text = _OPTIONS_JSON.encode(self.options)
        meta = {
            "pipeline": PIPELINE_NAME,
            "options_json": text,
            "seed": self.seed,
            "initialised": self.initialised,
            "t": self.t,
            "filter_t": self.filter_t,
            "epochs": self.epochs,
            "anchor": None if self.anchor is None else [self.anchor.lat, self.anchor.lon, self.anchor.height],
            "riss": self.riss,
            "clock_seen": self.clock_seen,
            "heading_known": self.heading_known,
            "carrier_sats": list(self.carrier.sats),
            "fault_keys": list(self.faults),
            "still_epochs": self.still_epochs,
            "noise_level": self.noise.to_list(),
        }
        arrays = {
            "particles": self.cloud.particles,
            "log_weights": self.cloud.log_weights,
            "cov": self.cloud.cov,
            "carrier": self.carrier.table,
            # an array, not JSON: some forty histories of four floats each were a third of the header's
            # encoding and decoding time, every epoch
            "faults": np.array(list(self.faults.values()), dtype=float).reshape(
                len(self.faults), _FAULT_FIELDS
            ),
        }
        if self.tdcp.receiver is not None:  # only sessions using phase differences: others keep their layout
            meta["tdcp_head"], meta["tdcp_sats"], arrays["tdcp"] = self.tdcp.to_parts()
        known = self.cloud.known_moments(layout.ANGLES)
        if known is not None:  # the UPF's step computed them: the next epoch starts from them
            arrays["moments_mean"], arrays["moments_cov"] = known
        return state_format.pack(meta, arrays)


def decode_session(blob: bytes) -> GnssSession:
    meta, arrays = state_format.unpack(blob)
    if meta.get("pipeline") != PIPELINE_NAME:
        raise state_format.StateFormatError("state does not belong to the gnss_tight pipeline")
    anchor = None if meta["anchor"] is None else GeodeticAnchor(*meta["anchor"])
    if arrays["particles"].shape[-1] != layout.DIM or arrays["cov"].shape != (layout.DIM, layout.DIM):
        # States written before the gyro-bias and wheel-scale components were added (13 components).
        raise state_format.StateFormatError(
            f"gnss_tight state has {arrays['particles'].shape[-1]} components; this version uses {layout.DIM}"
        )
    cloud = Cloud(arrays["particles"], arrays["log_weights"], arrays["cov"])
    if "moments_mean" in arrays:
        mean, cov = arrays["moments_mean"], arrays.get("moments_cov", np.zeros(0))
        if mean.shape != (layout.DIM,) or cov.shape != (layout.DIM, layout.DIM):
            raise state_format.StateFormatError(
                f"gnss_tight state's cloud moments are corrupt: mean {mean.shape}, covariance {cov.shape}"
            )
        cloud.remember_moments(layout.ANGLES, mean, cov)
    try:
        sats = [str(sat) for sat in meta.get("carrier_sats", [])]
        carrier = CarrierTable(sats, np.asarray(arrays.get("carrier", np.zeros((0, 6))), dtype=float))
    except (ValueError, TypeError) as error:
        raise state_format.StateFormatError(
            f"gnss_tight state's carrier tracks are corrupt: {error}"
        ) from None
    options, text = _options(meta)
    tdcp = PhaseHistory()
    if "tdcp_head" in meta:
        try:
            tdcp = PhaseHistory.from_parts(
                meta["tdcp_head"], meta.get("tdcp_sats", []), arrays.get("tdcp", np.zeros((0, 2)))
            )
        except (ValueError, TypeError) as error:
            raise state_format.StateFormatError(
                f"gnss_tight state's phase history is corrupt: {error}"
            ) from None
    return GnssSession(
        options,
        int(meta["seed"]),
        meta["initialised"],
        meta["t"],
        meta["filter_t"],
        meta["epochs"],
        anchor,
        meta["riss"],
        dict(meta["clock_seen"]),
        cloud,
        bool(meta.get("heading_known", False)),
        carrier,
        _faults(meta, arrays),
        int(meta.get("still_epochs", 0)),
        _noise(meta),
        text,
        tdcp,
    )


_OPTIONS_JSON = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


@functools.lru_cache(maxsize=256)
def _parsed_options(text: str) -> dict[str, Any]:
    """The options a state's ``options_json`` holds, parsed once per distinct text (a session's options
    do not change between its epochs); callers copy it, and the pipeline never writes to its options."""
    options = json.loads(text)
    if not isinstance(options, dict):
        raise TypeError("not a JSON object")
    return options


def _options(meta: dict[str, Any]) -> tuple[dict[str, Any], str | None]:
    """A decoded state's options and the text they came from (states written before ``options_json`` hold
    the options themselves: no text)."""
    text = meta.get("options_json")
    if text is None:
        return meta["options"], None
    try:
        if not isinstance(text, str):
            raise TypeError("not a string")
        return dict(_parsed_options(text)), text
    except (ValueError, TypeError) as error:
        raise state_format.StateFormatError(f"gnss_tight state's options are corrupt: {error}") from None


def _noise(meta: dict[str, Any]) -> NoiseLevel:
    """The noise level of a decoded state (no history when written before it)."""
    try:
        return NoiseLevel.from_list(meta.get("noise_level"))
    except (ValueError, TypeError) as error:
        raise state_format.StateFormatError(f"gnss_tight state's noise level is corrupt: {error}") from None


_FAULT_FIELDS = 4
"""Per fault history: epochs beyond the gate in a row, epochs agreeing in a row, excluded (0/1), last seen t."""


def _faults(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> dict[str, list[float]]:
    """The fault histories of a decoded state, whichever layout wrote them."""
    if "fault_keys" in meta:
        keys = [str(key) for key in meta["fault_keys"]]
        table = arrays.get("faults", np.zeros((0, _FAULT_FIELDS)))
        if table.shape != (len(keys), _FAULT_FIELDS):
            raise state_format.StateFormatError(
                f"gnss_tight state's fault histories are corrupt: {len(keys)} keys, array {table.shape}"
            )
        return dict(zip(keys, table.tolist(), strict=True))
    return {str(k): [float(x) for x in v] for k, v in meta.get("faults", {}).items()}


def empty_cloud() -> Cloud:
    """The placeholder cloud of a session not yet initialised (one particle at zero)."""
    return Cloud(np.zeros((1, layout.DIM)), np.zeros(1), np.eye(layout.DIM))


OWN_COVARIANCE_FILTERS = ("ukf", "upf")
"""Filters whose particles carry a covariance of their own (``Cloud.cov``); the PF's particles are points."""


def session_covariance(session: GnssSession) -> np.ndarray:
    """The state covariance the filter's cloud stands for (for the UPF: the particles' spread plus their own
    covariance)."""
    filt = filter_for(session.options)
    return filt.covariance(session.cloud) if hasattr(filt, "covariance") else session.cloud.cov


def filter_for(options: Mapping[str, Any]) -> Any:
    """The particle filter (UKF, PF or UPF) a session's options name, with their settings."""
    name = options["filter"]
    cls = PARTICLE_FILTERS[name]
    if name == "ukf":
        return cls()
    if name == "upf":
        # States stored before the option existed carry the value that was then built in (1).
        spread = options.get("spread_fraction", 1.0)
        return cls(resample_threshold=options["resample_threshold"], spread_fraction=spread)
    return cls(resample_threshold=options["resample_threshold"])


def cloud_moments(session: GnssSession) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's weighted mean, the azimuth averaged on the circle (a plain average of particles at +179
    and -179 deg, a vehicle heading south, would point north), and the covariance it stands for
    (``session_covariance``); the UPF's, its spread plus their own covariance, from the same moments."""
    cloud = session.cloud
    if len(cloud.particles) == 1:
        single: np.ndarray = cloud.particles[0].copy()
        return single, session_covariance(session)
    mean, spread = cloud.moments(layout.ANGLES)
    if session.options["filter"] == "upf":  # UnscentedParticleFilter.covariance without a second pass
        return mean, spread + cloud.cov
    return mean, session_covariance(session)

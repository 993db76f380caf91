"""Service configuration from ``EDGEPOS_*`` environment variables (see docs/service.md)."""

from __future__ import annotations

import ipaddress
import os
import secrets
import sys
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from edgepos.geo import GeodeticOrigin
from edgepos.store.ratelimit import RateLimit

LogLevel = Literal["critical", "error", "warning", "info", "debug"]


class Settings(BaseSettings):
    """Every knob of the service; each field is read from ``EDGEPOS_<FIELD NAME>``."""

    model_config = SettingsConfigDict(env_prefix="EDGEPOS_", extra="ignore", case_sensitive=False)

    host: str = Field("127.0.0.1", description="Address to listen on.")
    port: int = Field(8000, ge=0, le=65535, description="TCP port to listen on.")
    workers: int = Field(
        1, ge=1, le=64, description="Worker processes (>1 needs a shared store: SQLite or Redis)."
    )
    admin_key: SecretStr | None = Field(
        None,
        description="Bearer key for RSU writes and admin access to every session. When unset a random "
        "key is generated at start-up, printed once to stderr and written to admin_key_file.",
    )
    read_key: SecretStr | None = Field(
        None,
        description="Bearer key that opens only the read-only location routes: the MEC 013 adapter under "
        "/location/v3 and the fix stream (GET /v1/stream/fixes, every session's). Unset: only the admin key "
        "opens them. At least 32 characters, and not the admin key.",
    )
    callback_hosts: str = Field(
        "127.0.0.1,::1,localhost",
        description="Comma-separated host names or addresses that location subscriptions may send "
        "notifications to (callbackReference); a callback on any other host is refused with 422. The "
        "default allows this machine only.",
    )
    location_poll_s: float = Field(
        1.0,
        ge=0.01,
        le=60.0,
        allow_inf_nan=False,
        description="How often the location notifier compares the vehicles' latest fixes with the zones of "
        "the subscriptions (s): a zone entry is notified within about this long of the fix that shows it.",
    )
    callback_timeout_s: float = Field(
        5.0, gt=0, le=60.0, allow_inf_nan=False, description="Timeout of one notification POST (s)."
    )
    callback_backoff_s: float = Field(
        1.0,
        gt=0,
        le=3600.0,
        allow_inf_nan=False,
        description="Wait before the first retry of a failed notification (s); it doubles with each further "
        "failure, up to 300 s.",
    )
    callback_max_failures: int = Field(
        5,
        ge=1,
        le=100,
        description="Consecutive failed deliveries after which a location subscription expires (is deleted).",
    )
    admin_key_file: Path = Field(
        Path("edgepos-admin.key"), description="Where a generated admin key is written (mode 0600)."
    )
    store: str = Field(
        "memory",
        description="'memory' (one process), 'sqlite:///path.db' (several workers on one box) or "
        "'redis://host:port/db' (any worker of any replica; also rediss:// and unix://) or "
        "'redis-cluster://host:port[,host:port...]' (Redis Cluster; see docs/redis.md).",
    )
    redis_wait_replicas: int = Field(
        0,
        ge=0,
        le=16,
        description=(
            "Redis only: replicas that must hold a batch (Redis WAIT) before it is acknowledged; 0 "
            "acknowledges once the primary has it. A batch that does not reach them within "
            "EDGEPOS_REDIS_WAIT_TIMEOUT_MS is a 503 unavailable saying so, and is not acknowledged; it "
            "is on the primary, so the same batch sent again is answered (from the stored answer) once "
            "the replicas have it (docs/redis.md)."
        ),
    )
    redis_wait_timeout_ms: int = Field(
        500, ge=1, le=60_000, description="Redis only: how long a batch waits for those replicas (ms)."
    )
    max_sessions: int = Field(10_000, ge=1, description="Live sessions allowed at once (429 beyond).")
    session_ttl_s: float = Field(
        3600.0,
        gt=0,
        allow_inf_nan=False,
        description=(
            "A session with no applied batch for this many seconds (since its last batch, or its "
            "creation) expires and is removed."
        ),
    )
    max_batch_measurements: int = Field(
        1000,
        ge=1,
        le=100_000,
        description=(
            "Measurements allowed in one batch; more gives 422 invalid_request (field measurements)."
        ),
    )
    max_body_bytes: int = Field(
        1_048_576,
        ge=1024,
        description=(
            "Largest request body in bytes; larger gives 413 payload_too_large before anything is parsed."
        ),
    )
    max_ephemerides_bytes: int = Field(
        16_777_216,
        ge=1024,
        le=1_073_741_824,
        description="Largest navigation file PUT /v1/ephemerides accepts, in bytes (413 beyond, checked "
        "before parsing); replaces max_body_bytes on that route.",
    )
    max_base_observations_bytes: int = Field(
        16_777_216,
        ge=1024,
        le=1_073_741_824,
        description="Largest base-station observation upload (RINEX 3 or RTCM 3) POST "
        "/v1/base-stations/{id}/observations and .../rtcm accept, in bytes (413 beyond, checked before "
        "parsing; five minutes of a 1 Hz multi-GNSS RINEX file are about 2 MB).",
    )
    base_window_epochs: int = Field(
        900,
        ge=10,
        le=100_000,
        description="Base epochs of corrections kept per reference station (the newest; older ones are "
        "dropped): 900 is 15 min at 1 Hz, more than the largest max_correction_age_s (600 s).",
    )
    max_inflight: int = Field(
        32,
        ge=1,
        le=10_000,
        description=(
            "Requests one worker works on at once. The rest wait in line before their body is read, so "
            "that the requests in progress finish quickly: without the line an overloaded worker "
            "interleaves every request and a healthy Redis round trip can exceed its socket timeout. "
            "/healthz, /readyz and /metrics skip the line; edgepos_requests_waiting shows its length."
        ),
    )
    queue_timeout_s: float = Field(
        30.0,
        gt=0,
        allow_inf_nan=False,
        description="Longest a request waits in that line before it is answered 503 with Retry-After.",
    )
    batch_cpu_budget_ms: float = Field(
        50.0,
        ge=1.0,
        le=10_000.0,
        allow_inf_nan=False,
        description="Most CPU one batch (or one session's creation) may cost on this server, as the pipelines' "
        "cost models predict it (ms): a session whose options could not fit one epoch in it, or a batch "
        "predicted to cost more, is refused with 422 naming the bound. Keeps one vehicle from taking the CPU "
        "that every other vehicle on the worker needs.",
    )
    scheduler_slice_ms: float = Field(
        10.0,
        ge=0.0,
        le=10_000.0,
        allow_inf_nan=False,
        description="Batches predicted to cost more CPU than this (ms) are filtered in the heavy lane (worker "
        "processes), the rest in the light lane (EDGEPOS_LIGHT_LANE), so a heavy batch never delays a light one.",
    )
    light_lane: Literal["loop", "thread"] = Field(
        "thread",
        description="Where the light lane filters its batches: 'thread', on one filter thread of this process, "
        "which releases the interpreter lock while a batch's run of epochs is in compiled code, so that the "
        "event loop serves other requests meanwhile (measured: 1.06-1.36 times the epochs/s of 'loop' for one "
        "worker under a saturating load, about the same for two, docs/benchmarks.md); 'loop', on the event "
        "loop's own thread between two reads of its sockets (a batch holds the loop for at most about the "
        "slice).",
    )
    heavy_workers: int = Field(
        1,
        ge=0,
        le=64,
        description="Worker processes of the heavy lane, per service worker (started on the first heavy batch); "
        "0 runs heavy batches on a second thread instead (sharing the interpreter lock with the light lane).",
    )
    max_queued_per_vehicle: int = Field(
        2,
        ge=1,
        le=64,
        description="Requests one session (one vehicle) may have waiting for or in the filter at once; beyond "
        "it 429 with Retry-After. A vehicle's batches are applied one at a time in seq order anyway.",
    )
    rate_limit_per_s: float = Field(
        50.0,
        ge=0,
        allow_inf_nan=False,
        description=(
            "Requests per second one session's token may make, sustained, counted in the store so that "
            "it holds across workers and replicas; beyond it 429 rate_limited with Retry-After. 0 turns "
            "it off. The admin key is not limited."
        ),
    )
    rate_limit_burst: int = Field(
        100, ge=1, description="Requests a session's token may make at once before the rate applies."
    )
    stream_buffer: int = Field(
        10_000,
        ge=10,
        le=1_000_000,
        description="Fixes the fix stream (GET /v1/stream/fixes) keeps for consumers that resume with "
        "Last-Event-ID, across all sessions; a consumer further behind is told how many it missed.",
    )
    stream_queue: int = Field(
        1_000,
        ge=10,
        le=1_000_000,
        description="Fixes one stream consumer may have waiting to be sent; a consumer that falls further "
        "behind is dropped with a final event saying so (it resumes with Last-Event-ID), so a slow "
        "consumer never holds back the others or the vehicles.",
    )
    stream_max_consumers: int = Field(
        64,
        ge=1,
        le=100_000,
        description=(
            "Fix streams one worker serves at once; beyond, 503 with Retry-After. Streams do not take "
            "EDGEPOS_MAX_INFLIGHT slots."
        ),
    )
    stream_interval_ms: float = Field(
        50.0,
        ge=0,
        le=1000,
        allow_inf_nan=False,
        description="Under load a worker reads the fix stream and writes to its consumers at most once per this "
        "many ms, all that came meanwhile at once (0: as soon as each batch's fixes arrive); fewer, larger writes "
        "keep the consumers from delaying the vehicles' answers.",
    )
    stream_ping_s: float = Field(
        15.0,
        gt=0,
        le=300,
        allow_inf_nan=False,
        description="Seconds between keep-alive comments on an idle fix stream, so proxies do not cut it.",
    )
    ws_max_connections: int = Field(
        1024,
        ge=1,
        le=100_000,
        description="Batch WebSockets (/v1/sessions/{id}/ws) one worker holds open at once; a handshake beyond "
        "is refused 503 with Retry-After (each link holds buffers; a stolen token must not open thousands).",
    )
    ws_idle_timeout_s: float = Field(
        300.0,
        gt=0,
        le=86_400,
        allow_inf_nan=False,
        description="Seconds a batch WebSocket (/v1/sessions/{id}/ws) may stay without a frame from the "
        "vehicle before the server closes it (code 1000); protocol pings alone do not keep it open.",
    )
    origin_lat: float | None = Field(
        None,
        ge=-90,
        le=90,
        allow_inf_nan=False,
        description=(
            "Site origin latitude, WGS-84 decimal degrees. Set with EDGEPOS_ORIGIN_LON to get "
            "latitude/longitude in fixes (and the map's latitude/longitude grid)."
        ),
    )
    origin_lon: float | None = Field(
        None,
        ge=-180,
        le=180,
        allow_inf_nan=False,
        description="Site origin longitude, WGS-84 decimal degrees.",
    )
    origin_height: float = Field(
        0.0, allow_inf_nan=False, description="Site origin ellipsoidal height (m), used with origin_lat/lon."
    )
    cors_origins: str = Field(
        "", description="Comma-separated origins allowed by CORS ('*' for any); empty disables CORS."
    )
    log_level: LogLevel = Field("info", description="Log level of the JSON-lines logs.")
    demo_rsus: bool = Field(
        False,
        description=(
            "Preload the RSU map of the RSU + IMU paper's scenario "
            "(edgepos.sim.scenarios.rsu_imu_paper_scenario) at start-up."
        ),
    )
    auth: Literal["on", "off"] = Field(
        "on",
        description="'off' lets every request in with admin rights and no credentials, for a lab bench "
        "only: refused unless lab is true.",
    )
    lab: bool = Field(
        False,
        description=(
            "Declares the instance a lab bench (edgepos serve --lab): the only way EDGEPOS_AUTH=off, or "
            "EDGEPOS_VEHICLE_AUTH=open on a non-loopback address, is accepted; the service then warns "
            "on stderr (and, with auth off, in its log)."
        ),
    )
    vehicle_auth: Literal["key", "jwt", "open"] = Field(
        "key",
        description="What opening a session takes besides the admin key (which opens one for any vehicle). "
        "'key': the vehicle's own key from the registry (POST /v1/vehicles), for its own vehicle_id only. "
        "'jwt': a token signed by the fleet operator (ES256 or RS256, keys from vehicle_jwks, sub = vehicle "
        "id, aud = vehicle_jwt_audience, exp required), checked without a registry read. 'open': no "
        "credential (anyone may open a session as any vehicle); refused on a non-loopback host unless lab.",
    )
    vehicle_jwks: Path | None = Field(
        None,
        description="JWKS file with the fleet operator's public keys (needed with vehicle_auth 'jwt'); a file "
        "that does not parse stops the service at start-up.",
    )
    vehicle_jwt_audience: str = Field(
        "edgepos", min_length=1, description="The 'aud' a vehicle token must carry (vehicle_auth 'jwt')."
    )
    auth_failure_rate_per_s: float = Field(
        0.2,
        gt=0,
        allow_inf_nan=False,
        description=(
            "Failed authentications allowed per second, sustained, per client address and per "
            "credential presented; beyond it 429 rate_limited with Retry-After, and an address past it "
            "cannot open sessions until its budget refills."
        ),
    )
    auth_failure_burst: int = Field(
        20, ge=1, description="Failed authentications a client address or credential may make at once."
    )
    session_create_rate_per_s: float = Field(
        0.2,
        gt=0,
        allow_inf_nan=False,
        description="Sessions one vehicle credential may open per second, sustained (429 beyond); the admin "
        "key is not limited.",
    )
    session_create_burst: int = Field(
        10, ge=1, description="Sessions one vehicle credential may open at once before that rate applies."
    )
    session_create_address_rate_per_s: float = Field(
        20.0,
        gt=0,
        allow_inf_nan=False,
        description="Sessions opened per second, sustained, from one client address with vehicle "
        "credentials (or none, with vehicle_auth 'open'); generous because a fleet may share one NAT address.",
    )
    session_create_address_burst: int = Field(
        200, ge=1, description="Sessions one client address may open at once before that rate applies."
    )

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower_level(cls, value: object) -> object:
        return value.lower() if isinstance(value, str) else value

    @field_validator("store")
    @classmethod
    def _check_store(cls, value: str) -> str:
        sqlite = value.startswith("sqlite:///") and len(value) > len("sqlite:///")
        redis = value.startswith(("redis://", "rediss://", "unix://", "redis-cluster://"))
        if value != "memory" and not sqlite and not redis:
            raise ValueError(
                "store must be 'memory', 'sqlite:///path.db', 'redis://host:port/db' or "
                "'redis-cluster://host:port[,host:port...]'"
            )
        if value.startswith("redis-cluster://"):
            from edgepos.store.redis_cluster import parse_cluster_url

            parse_cluster_url(value)  # a wrong node list or option stops the start, naming it
        return value

    @model_validator(mode="after")
    def _wait_needs_redis(self) -> Settings:
        if self.redis_wait_replicas and not self.store.startswith(
            ("redis://", "rediss://", "unix://", "redis-cluster://")
        ):
            raise ValueError(
                "redis_wait_replicas (EDGEPOS_REDIS_WAIT_REPLICAS) needs a Redis store (EDGEPOS_STORE)"
            )
        return self

    @model_validator(mode="after")
    def _read_key(self) -> Settings:
        if self.read_key is None:
            return self
        key = self.read_key.get_secret_value()
        if len(key) < 32:
            raise ValueError("read_key (EDGEPOS_READ_KEY) must be at least 32 characters (a random secret)")
        if self.admin_key is not None and key == self.admin_key.get_secret_value():
            raise ValueError("read_key (EDGEPOS_READ_KEY) must differ from the admin key")
        return self

    @field_validator("callback_hosts")
    @classmethod
    def _check_callback_hosts(cls, value: str) -> str:
        hosts = [host.strip() for host in value.split(",") if host.strip()]
        bad = [host for host in hosts if "/" in host or " " in host]
        if bad:
            raise ValueError(f"callback_hosts: {bad[0]!r} is not a host name or address")
        return value

    @model_validator(mode="after")
    def _origin_pair(self) -> Settings:
        if (self.origin_lat is None) != (self.origin_lon is None):
            raise ValueError("set both origin_lat and origin_lon, or neither")
        return self

    @model_validator(mode="after")
    def _auth_off_only_in_a_lab(self) -> Settings:
        if self.auth == "off" and not self.lab:
            raise ValueError(
                "auth is 'off' (EDGEPOS_AUTH=off), which lets anyone read and write every session and the RSU "
                "map; refused unless this is declared a lab: set EDGEPOS_LAB=true or pass `edgepos serve --lab`"
            )
        return self

    @model_validator(mode="after")
    def _vehicle_auth_settings(self) -> Settings:
        if self.vehicle_auth == "jwt" and self.vehicle_jwks is None:
            raise ValueError(
                "vehicle_auth is 'jwt' (EDGEPOS_VEHICLE_AUTH=jwt) but no key set is given: set EDGEPOS_VEHICLE_JWKS "
                "to the fleet operator's JWKS file"
            )
        if self.vehicle_auth == "open" and not self.lab and not is_loopback(self.host):
            raise ValueError(
                f"vehicle_auth is 'open' (EDGEPOS_VEHICLE_AUTH=open) on {self.host!r}, a non-loopback address: anyone "
                "who reaches it could open a session as any vehicle and feed its neighbours a false track; refused "
                "unless this is declared a lab (EDGEPOS_LAB=true or `edgepos serve --lab`). Register vehicles "
                "(POST /v1/vehicles) and keep the default 'key', or use 'jwt'"
            )
        return self

    @property
    def auth_enabled(self) -> bool:
        return self.auth == "on"

    @property
    def rate_limit(self) -> RateLimit | None:
        """The per-session request-rate limit, or None when it is off."""
        if self.rate_limit_per_s == 0:
            return None
        return RateLimit(self.rate_limit_per_s, self.rate_limit_burst)

    @property
    def batch_cpu_budget_s(self) -> float:
        return self.batch_cpu_budget_ms / 1000.0

    @property
    def auth_failure_limit(self) -> RateLimit:
        """Failed authentications per client address and per credential."""
        return RateLimit(self.auth_failure_rate_per_s, self.auth_failure_burst)

    @property
    def session_create_limit(self) -> RateLimit:
        """Session creations per vehicle credential."""
        return RateLimit(self.session_create_rate_per_s, self.session_create_burst)

    @property
    def session_create_address_limit(self) -> RateLimit:
        """Session creations per client address (vehicle credentials or none)."""
        return RateLimit(self.session_create_address_rate_per_s, self.session_create_address_burst)

    @property
    def callback_host_set(self) -> frozenset[str]:
        """The hosts notifications may go to, lower-case, IPv6 addresses without brackets."""
        return frozenset(
            host.strip().strip("[]").lower() for host in self.callback_hosts.split(",") if host.strip()
        )

    @property
    def cors_origin_list(self) -> list[str]:
        return [origin.strip() for origin in self.cors_origins.split(",") if origin.strip()]

    @property
    def origin(self) -> GeodeticOrigin | None:
        if self.origin_lat is None or self.origin_lon is None:
            return None
        return GeodeticOrigin.from_degrees(self.origin_lat, self.origin_lon, self.origin_height)


def is_loopback(host: str) -> bool:
    """True for an address only this machine can reach (127.0.0.0/8, ::1, localhost)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def write_secret_file(path: Path, secret: str) -> Path:
    """Write ``secret`` to ``path`` readable by its owner only (0600), replacing any old file."""
    path = path.expanduser().resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(descriptor, 0o600)
        os.write(descriptor, (secret + "\n").encode())
    finally:
        os.close(descriptor)
    return path


def ensure_admin_key(settings: Settings) -> Settings:
    """Settings with an admin key: the configured one, or a fresh random one that is printed once
    to stderr and saved (0600) to ``admin_key_file`` so the operator can find it later."""
    if settings.admin_key is not None and settings.admin_key.get_secret_value():
        return settings
    key = secrets.token_urlsafe(32)
    path = write_secret_file(settings.admin_key_file, key)
    print(
        f"edgepos: EDGEPOS_ADMIN_KEY is not set; generated admin key {key} "
        f"(also saved to {path}, mode 0600; set EDGEPOS_ADMIN_KEY to choose your own)",
        file=sys.stderr,
        flush=True,
    )
    return settings.model_copy(update={"admin_key": SecretStr(key)})

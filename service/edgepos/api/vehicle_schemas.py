"""Wire schemas of the vehicle registry (``/v1/vehicles``): registering, importing, listing and revoking
vehicles and their keys (docs/security.md). The shared bases and patterns are in :mod:`edgepos.api.schemas`."""

from __future__ import annotations

from pydantic import ConfigDict, Field, field_validator

from edgepos.api.schemas import VEHICLE_ID_PATTERN, RequestModel, ResponseModel


class VehicleCreate(RequestModel):
    """Body of POST /v1/vehicles: the vehicle to register."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"vehicle_id": "bus-42"}]})

    vehicle_id: str = Field(
        pattern=VEHICLE_ID_PATTERN,
        description="The vehicle's identifier, as its sessions will name it: 1-128 characters of letters, "
        "digits, space and . _ : + @ / -.",
    )


MAX_VEHICLES_PER_IMPORT = 5_000


class VehicleImport(RequestModel):
    """Body of POST /v1/vehicles/bulk: many vehicles at once (each id once)."""

    model_config = ConfigDict(
        json_schema_extra={
            "description": "Many vehicles at once. Each vehicle_id at most once per request: a repeated id "
            "is refused (422, field 'vehicles'), which JSON Schema cannot state for objects.",
            "examples": [{"vehicles": [{"vehicle_id": "bus-41"}, {"vehicle_id": "bus-42"}]}],
        }
    )

    vehicles: list[VehicleCreate] = Field(
        min_length=1,
        max_length=MAX_VEHICLES_PER_IMPORT,
        description=f"1-{MAX_VEHICLES_PER_IMPORT} vehicles, no id twice.",
    )

    @field_validator("vehicles")
    @classmethod
    def _distinct(cls, value: list[VehicleCreate]) -> list[VehicleCreate]:
        seen: set[str] = set()
        for number, vehicle in enumerate(value):
            if vehicle.vehicle_id in seen:
                raise ValueError(f"vehicles[{number}].vehicle_id {vehicle.vehicle_id!r} is listed twice")
            seen.add(vehicle.vehicle_id)
        return value


class VehicleOut(ResponseModel):
    """A registered vehicle (never its key)."""

    vehicle_id: str = Field(description="The vehicle's identifier.")
    created_at: float = Field(description="Registration time (Unix seconds, server clock).")
    key_issued_at: float = Field(description="When its current key was issued (Unix seconds, server clock).")


class VehicleKeyIssued(VehicleOut):
    """A vehicle with its new key: shown once, stored only as a hash. Give it to the vehicle; it opens
    sessions for this vehicle only (``Authorization: Bearer <key>`` on POST /v1/sessions)."""

    key: str = Field(description="The vehicle's key (starts with 'evk_'); shown once.")


class VehicleImported(ResponseModel):
    """Answer to POST /v1/vehicles/bulk."""

    registered: list[VehicleKeyIssued] = Field(description="Vehicles registered now, each with its key.")
    already_registered: list[str] = Field(
        description="Ids that were registered before and were left as they are (their keys unchanged)."
    )


class VehicleList(ResponseModel):
    """A page of GET /v1/vehicles, ordered by vehicle id."""

    vehicles: list[VehicleOut] = Field(description="Registered vehicles of this page.")
    total: int = Field(description="Registered vehicles in all.")
    next_after: str | None = Field(description="Pass as ?after= for the next page; null on the last page.")


class VehicleRevoked(ResponseModel):
    """Answer to DELETE /v1/vehicles/{vehicle_id}."""

    vehicle_id: str = Field(description="The vehicle removed from the registry; its key opens nothing now.")
    ended_session: str | None = Field(description="Its live session, ended with it; null when it had none.")


# -- fixes ---------------------------------------------------------------------------------------

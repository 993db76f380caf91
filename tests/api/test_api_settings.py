"""Settings from EDGEPOS_* variables."""

from __future__ import annotations

import pytest
from edgepos.api.settings import Settings
from pydantic import ValidationError


def test_defaults():
    settings = Settings()
    assert (settings.host, settings.port, settings.workers, settings.store) == (
        "127.0.0.1",
        8000,
        1,
        "memory",
    )
    assert settings.admin_key is None and settings.origin is None and settings.cors_origin_list == []
    assert settings.demo_rsus is False and settings.log_level == "info"


def test_environment_variables(monkeypatch):
    monkeypatch.setenv("EDGEPOS_PORT", "9100")
    monkeypatch.setenv("EDGEPOS_STORE", "sqlite:///var/edgepos.db")
    monkeypatch.setenv("EDGEPOS_ADMIN_KEY", "k" * 32)
    monkeypatch.setenv("EDGEPOS_CORS_ORIGINS", "https://a.example, https://b.example")
    monkeypatch.setenv("EDGEPOS_ORIGIN_LAT", "48.1")
    monkeypatch.setenv("EDGEPOS_ORIGIN_LON", "11.5")
    monkeypatch.setenv("EDGEPOS_DEMO_RSUS", "true")
    monkeypatch.setenv("EDGEPOS_LOG_LEVEL", "DEBUG")
    settings = Settings()
    assert settings.port == 9100 and settings.store == "sqlite:///var/edgepos.db"
    assert settings.admin_key.get_secret_value() == "k" * 32
    assert "k" * 32 not in repr(settings)
    assert settings.cors_origin_list == ["https://a.example", "https://b.example"]
    assert settings.origin is not None and settings.demo_rsus and settings.log_level == "debug"


@pytest.mark.parametrize(
    "values",
    [
        {"store": "mongodb://x"},
        {"store": "sqlite:///"},
        {"origin_lat": 10.0},
        {"origin_lat": 95.0, "origin_lon": 0.0},
        {"max_sessions": 0},
        {"session_ttl_s": float("inf")},
        {"log_level": "loud"},
    ],
)
def test_invalid_settings_are_refused(values):
    with pytest.raises(ValidationError):
        Settings(**values)


def test_auth_off_is_refused_unless_the_instance_is_a_lab(monkeypatch):
    monkeypatch.setenv("EDGEPOS_AUTH", "off")
    with pytest.raises(ValidationError, match="EDGEPOS_LAB=true"):
        Settings()
    monkeypatch.setenv("EDGEPOS_LAB", "true")
    settings = Settings()
    assert not settings.auth_enabled and settings.lab
    assert Settings(auth="on").auth_enabled

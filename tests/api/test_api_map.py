"""The operator map's page and GET /v1/status without a browser (the browser test is test_api_map_browser):
the page is served whole from the package with a policy that keeps it on this server, and the status route
is admin-only and counts exactly what the service did in its window."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
from apihelp import ADMIN, assert_error, batch_body, bearer, make_settings, open_session, rsu_payload
from edgepos.api.app import create_app
from edgepos.api.recent import RecentWindow, quantile
from fastapi.testclient import TestClient

STATIC = Path(__file__).resolve().parents[2] / "service" / "edgepos" / "api" / "static"


def test_map_page_is_served_with_a_policy_that_keeps_it_on_this_server(client: TestClient):
    response = client.get("/map")  # no key: the page holds no data, it asks for the key
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    policy = response.headers["content-security-policy"]
    for directive in (
        "default-src 'none'",
        "script-src 'self'",
        "connect-src 'self'",
        "img-src 'self' data:",
    ):
        assert directive in policy
    assert response.headers["referrer-policy"] == "no-referrer"
    assets = re.findall(r'(?:src|href)="([^"]+)"', response.text)
    assert set(assets) == {
        "/static/map/map.css",
        "/static/map/map.js",
        "/static/swagger-ui/favicon-32x32.png",
    }
    for asset in assets:
        assert client.get(asset).status_code == 200, asset


def test_map_files_name_no_outside_address():
    """Nothing the page loads names another host (the only URL in them is the SVG namespace, an identifier)."""
    for name in ("index.html", "map.js", "map.css"):
        text = (STATIC / "map" / name).read_text(encoding="utf-8")
        urls = set(re.findall(r"(?:https?:)?//[A-Za-z0-9.-]+\.[A-Za-z]{2,}[^\s\"')]*", text))
        assert urls <= {"http://www.w3.org/2000/svg"}, (name, urls)


def test_the_key_goes_in_the_authorization_header_only():
    script = (STATIC / "map" / "map.js").read_text(encoding="utf-8")
    assert "new EventSource" not in script  # it cannot send the header: the stream is read with fetch
    assert "localStorage" not in script  # sessionStorage: gone with the tab
    assert '"Bearer " + key' in script
    assert not re.search(r"[?&](key|token|admin)=", script)


def test_status_needs_the_admin_key(client: TestClient):
    assert_error(client.get("/v1/status"), 401, "unauthorized")
    assert_error(client.get("/v1/status", headers=bearer("not-the-key")), 401, "unauthorized")
    _, token = open_session(client)
    assert_error(client.get("/v1/status", headers=token), 403, "forbidden")


def test_status_counts_the_batches_of_its_window(client: TestClient):
    before = client.get("/v1/status", headers=ADMIN).json()
    assert before["batch_requests"] == 0 and before["batch_latency_p99_s"] is None
    assert before["epochs_per_s"] == before["batches_per_s"] == 0.0
    assert before["origin"] is None and before["stream_consumers"] == 0
    session_id, _ = open_session(client)
    epochs = [3, 5, 2]
    first = 0
    for seq, count in enumerate(epochs, start=1):
        response = client.post(
            f"/v1/sessions/{session_id}/batches", json=batch_body(seq, first, count), headers=ADMIN
        )
        assert response.status_code == 200, response.text
        first += count
    late = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 1), headers=ADMIN)
    assert late.status_code == 409  # answered, not applied: in the p99, not in the rates
    status = client.get("/v1/status", headers=ADMIN).json()
    assert status["sessions"] == 1
    assert status["window_s"] == 10.0
    assert status["epochs_per_s"] == pytest.approx(sum(epochs) / 10.0)
    assert status["batches_per_s"] == pytest.approx(len(epochs) / 10.0)
    assert status["batch_requests"] == len(epochs) + 1
    assert 0.0 < status["batch_latency_p99_s"] < 30.0


def test_status_gives_the_site_origin_in_radians(tmp_path: Path):
    settings = make_settings(tmp_path, origin_lat=48.137, origin_lon=11.575, origin_height=520.0)
    with TestClient(create_app(settings)) as client:
        assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        origin = client.get("/v1/status", headers=ADMIN).json()["origin"]
    assert origin == {"latitude": math.radians(48.137), "longitude": math.radians(11.575), "height": 520.0}


def test_recent_window_forgets_what_is_older_than_the_window():
    now = [100.0]
    window = RecentWindow(window_s=10.0, clock=lambda: now[0])
    window.add_batch(20)
    window.add_latency(0.5)
    now[0] = 105.0
    window.add_batch(10)
    for seconds in (0.001, 0.002, 0.003):
        window.add_latency(seconds)
    figures = window.figures()
    assert (figures.epochs_per_s, figures.batches_per_s, figures.batch_requests) == (3.0, 0.2, 4)
    assert figures.batch_latency_p99_s == 0.5
    now[0] = 110.5  # the first batch and the 0.5 s answer are 10.5 s old now
    figures = window.figures()
    assert (figures.epochs_per_s, figures.batches_per_s, figures.batch_requests) == (1.0, 0.1, 3)
    assert figures.batch_latency_p99_s == 0.003
    now[0] = 200.0
    assert window.figures().batch_latency_p99_s is None


def test_recent_window_forgets_as_it_writes():
    """Memory follows the rate even when nobody reads the figures."""
    now = [0.0]
    window = RecentWindow(window_s=10.0, clock=lambda: now[0])
    for step in range(1000):
        now[0] = step * 0.1
        window.add_latency(0.001)
        window.add_batch(1)
    assert len(window._latencies) == len(window._epochs) == 101  # 10 s at 10/s, both ends included


def test_recent_window_is_bounded():
    window = RecentWindow(window_s=10.0, max_events=5, clock=lambda: 0.0)
    for _ in range(8):
        window.add_batch(1)
    assert window.figures().epochs_per_s == 0.5


def test_quantile_is_the_nearest_rank():
    values = [float(v) for v in range(1, 101)]  # 1 .. 100
    assert quantile(values, 0.99) == 99.0
    assert quantile(values[::-1], 0.5) == 50.0
    assert quantile([7.0], 0.99) == 7.0
    assert quantile([1.0, 2.0], 0.99) == 2.0
    with pytest.raises(ValueError):
        quantile([], 0.99)

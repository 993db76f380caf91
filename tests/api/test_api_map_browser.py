"""The operator map in a real browser (Debian's chromium driven by Playwright, no downloaded browser) against a
real server process: every request to a host other than 127.0.0.1 is blocked and recorded; a wrong key is
refused and not kept; after ``edgepos simulate`` drives three vehicles, each marker sits where the API's fix
says (its data attributes and its drawn position), with the fix's heading and 95 % ellipse; the detail
panel shows the vehicle's models, NIS and a rejected measurement; the grid is latitude/longitude with
EDGEPOS_ORIGIN_LAT/LON. A screenshot goes to results/map.png."""

from __future__ import annotations

import asyncio
import math
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlparse

import httpx
import numpy as np
import pytest
from apihelp import ADMIN, ADMIN_KEY, wire
from edgepos.geo import GeodeticOrigin
from edgepos.loadgen import common
from edgepos.loadgen.localserver import clean_environment, running, serve_command
from edgepos.loadgen.simulate import SimulationResult, run_simulation

pytestmark = pytest.mark.slow

sync_api = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
RESULTS = Path(__file__).resolve().parents[2] / "results"
ORIGIN_DEG = (48.137, 11.575)
EPOCHS = 150
WAIT_MS = 20_000


def _centre(page, selector: str) -> tuple[float, float]:
    box = page.locator(selector).bounding_box()
    assert box is not None, selector
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (make chromium)")
    with sync_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM)
        yield launched
        launched.close()


def _server_environment(**extra: str) -> dict[str, str]:
    return clean_environment(
        EDGEPOS_ADMIN_KEY=ADMIN_KEY, EDGEPOS_DEMO_RSUS="true", EDGEPOS_LOG_LEVEL="warning", **extra
    )


def _guarded_page(browser) -> tuple[object, object, list[str], list[str]]:
    """A fresh browser context whose requests to any host but 127.0.0.1 are aborted and recorded, and a page
    of it whose script errors are recorded."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    outside: list[str] = []

    def guard(route) -> None:
        if urlparse(route.request.url).hostname == "127.0.0.1":
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort("blockedbyclient")

    context.route("**/*", guard)
    errors: list[str] = []
    page = context.new_page()
    page.on("pageerror", lambda error: errors.append(str(error)))
    return context, page, outside, errors


def _simulate(url: str, vehicles: int, epochs: int, **options: object) -> SimulationResult:
    simulation = run_simulation(
        url, vehicles=vehicles, admin_key=ADMIN_KEY, epochs=epochs, keep_sessions=True, **options
    )
    with ThreadPoolExecutor(1) as pool:  # Playwright's own event loop runs in this thread
        result = pool.submit(asyncio.run, simulation).result()
    assert [run.error for run in result.vehicles] == [None] * vehicles
    return result


def _wait_for_fix(page, vehicle_id: str, t: float) -> dict[str, str]:
    """The data attributes of the vehicle's marker once it shows the fix of time t."""
    marker = f"#vehicles g.vehicle[data-vehicle-id='{vehicle_id}']"
    page.wait_for_function(
        "([selector, t]) => { const g = document.querySelector(selector); return g && Number(g.dataset.t) === t; }",
        arg=[marker, t],
        timeout=WAIT_MS,
    )
    return page.eval_on_selector(marker, "g => ({...g.dataset})")


def test_map_in_a_browser(browser, tmp_path: Path):
    environment = _server_environment(
        EDGEPOS_ORIGIN_LAT=str(ORIGIN_DEG[0]), EDGEPOS_ORIGIN_LON=str(ORIGIN_DEG[1])
    )
    with running(serve_command(1), environment, tmp_path / "server.log", ready_timeout_s=300.0) as url:
        context, page, outside, errors = _guarded_page(browser)
        try:
            _drive_the_page(context, page, outside, errors, url)
        finally:
            context.close()


def _drive_the_page(context, page, outside: list[str], errors: list[str], url: str) -> None:
    page.goto(f"{url}/map")
    page.wait_for_selector("#login-form")

    # a wrong key: refused on the page, not kept, and the map stays closed
    page.fill("#key", "not-the-admin-key")
    page.click("#login-button")
    page.wait_for_selector("#login-error:not([hidden])")
    assert "Refused" in page.text_content("#login-error")
    assert page.evaluate("sessionStorage.getItem('edgepos.adminKey')") is None
    assert page.is_hidden("#app")

    page.fill("#key", ADMIN_KEY)
    page.click("#login-button")
    page.wait_for_selector("body[data-stream='live']", timeout=WAIT_MS)
    assert page.evaluate("sessionStorage.getItem('edgepos.adminKey')") == ADMIN_KEY
    assert ADMIN_KEY not in page.url

    rsus = httpx.get(f"{url}/v1/rsus", headers=ADMIN).json()["rsus"]
    assert page.locator("#rsus rect.rsu").count() == len(rsus) >= 2

    result = _simulate(url, 3, EPOCHS, batch_epochs=10)

    # one batch more for sim-1 with every RSU range 300 m long: refused by the pipeline, the panel says why
    first = result.vehicles[0]
    observations = common.vehicle_epochs(common.SCENARIOS["rsu-imu"](), 0, 0)[EPOCHS]
    measurements = [wire(o) for o in observations]
    for measurement in measurements:
        if measurement["type"] == "rsu":
            measurement["range"] += 300.0
    last_seq = httpx.get(f"{url}/v1/sessions/{first.session_id}", headers=ADMIN).json()["last_seq"]
    extra = httpx.post(
        f"{url}/v1/sessions/{first.session_id}/batches",
        json={"seq": last_seq + 1, "measurements": measurements},
        headers=ADMIN,
    )
    assert extra.status_code == 200, extra.text
    gated = [m for m in extra.json()["fixes"][-1]["measurements"] if not m["used"]]
    assert gated and all(m["reason"] for m in gated)

    origin = GeodeticOrigin.from_degrees(*ORIGIN_DEG)
    # the screen transform the RSUs' squares were drawn with: uniform scale, y down on screen
    (sa, ra), *others = [(_centre(page, f"#rsus rect[data-rsu-id='{r['id']}']"), r) for r in rsus]
    sb, rb = max(others, key=lambda item: math.dist((item[1]["x"], item[1]["y"]), (ra["x"], ra["y"])))
    scale = math.dist(sa, sb) / math.dist((ra["x"], ra["y"]), (rb["x"], rb["y"]))

    for run in result.vehicles:
        session = httpx.get(f"{url}/v1/sessions/{run.session_id}", headers=ADMIN).json()
        fix = session["last_fix"]
        returned = extra.json()["fixes"][-1] if run is first else run.fixes[-1]
        as_read = (
            (returned["t"], returned["x"], returned["y"])
            if run is first
            else (returned.t, returned.x, returned.y)
        )
        assert (
            fix["t"],
            fix["x"],
            fix["y"],
        ) == as_read  # the session's last fix is the one its batch returned
        marker = f"#vehicles g.vehicle[data-vehicle-id='{run.vehicle_id}']"
        data = _wait_for_fix(page, run.vehicle_id, fix["t"])
        assert data["sessionId"] == run.session_id and data["status"] == fix["status"]
        assert (float(data["x"]), float(data["y"])) == (fix["x"], fix["y"])  # the fix's own numbers, site m
        assert float(data["heading"]) == fix["heading"]
        # the 95 % ellipse of the fix's covariance: chi-square(2) 95 % quantile on the eigenvalues
        eigenvalues, eigenvectors = np.linalg.eigh(np.array(fix["position_covariance"]))
        k = math.sqrt(5.991464547107979)
        assert float(data["ellipseMajor"]) == pytest.approx(k * math.sqrt(eigenvalues[1]), rel=1e-9)
        assert float(data["ellipseMinor"]) == pytest.approx(k * math.sqrt(eigenvalues[0]), rel=1e-9)
        major = eigenvectors[:, 1]
        angle = float(data["ellipseAngle"])
        assert (
            abs(math.cos(angle) * major[1] - math.sin(angle) * major[0]) < 1e-6
        )  # parallel to the major axis
        # drawn where the fix is: the same screen transform as the RSUs' squares (y down on screen)
        cx, cy = _centre(page, f"{marker} ellipse")
        assert cx == pytest.approx(sa[0] + (fix["x"] - ra["x"]) * scale, abs=1.5)
        assert cy == pytest.approx(sa[1] - (fix["y"] - ra["y"]) * scale, abs=1.5)
        # the grid's latitude/longitude on the tangent plane agree with the fix's WGS-84 position
        geo = page.evaluate(
            "([x, y, o]) => window.edgeposMap.siteToGeo(x, y, o)",
            [fix["x"], fix["y"], {"latitude": origin.lat, "longitude": origin.lon, "height": 0.0}],
        )
        assert geo["latitude"] == pytest.approx(fix["latitude"], abs=2e-8)  # 2e-8 rad: 13 cm
        assert geo["longitude"] == pytest.approx(fix["longitude"], abs=2e-8)

    assert page.get_attribute("#grid", "data-kind") == "wgs84"
    assert page.locator("#grid line[data-kind='latitude']").count() >= 2
    assert page.locator("#grid line[data-kind='longitude']").count() >= 2
    page.wait_for_selector("#header[data-sessions='3']", state="attached", timeout=WAIT_MS)
    # the header's figures are the service's: the batches just sent are in its 10 s window
    page.wait_for_function(
        "() => Number(document.getElementById('header').dataset.batchRequests) > 0", timeout=WAIT_MS
    )
    assert float(page.get_attribute("#header", "data-epochs-per-s") or "0") > 0

    # the detail panel of sim-1: its pipeline, models, NIS history and the refused RSU measurements
    # the three vehicles start together and overlap: click this one's marker itself, not whatever is on top
    page.dispatch_event(
        f"#vehicles g.vehicle[data-vehicle-id='{first.vehicle_id}'] .body:not([visibility])", "click"
    )
    page.wait_for_selector("#panel:not([hidden])")
    page.wait_for_selector("#rejected li[data-type='rsu']", timeout=WAIT_MS)
    assert page.get_attribute("#panel", "data-vehicle-id") == first.vehicle_id
    assert "rsu_imu" in page.text_content("#panel-facts")
    last = extra.json()["fixes"][-1]
    shown = {
        row["model"]: float(row["probability"])
        for row in page.eval_on_selector_all("#models .model", "rows => rows.map(r => ({...r.dataset}))")
    }
    assert shown == last["model_probabilities"]
    assert all(m["reason"] in page.text_content("#rejected") for m in gated)
    assert int(page.get_attribute("#nis-plot", "data-points") or "0") > 10
    page.wait_for_selector("#session-facts dt:text('batches')", timeout=WAIT_MS)

    # zooming with the wheel keeps the site point under the cursor there, and the marker is redrawn at its fix
    ellipse = f"#vehicles g.vehicle[data-vehicle-id='{first.vehicle_id}'] ellipse"
    cursor = tuple(round(c) for c in _centre(page, ellipse))  # the browser's wheel events are at whole pixels
    width = page.locator(ellipse).bounding_box()["width"]
    stage = page.locator("#map").bounding_box()

    def under_cursor(view: dict[str, float]) -> tuple[float, float]:
        return (
            view["cx"] + (cursor[0] - stage["x"] - stage["width"] / 2) / view["scale"],
            view["cy"] - (cursor[1] - stage["y"] - stage["height"] / 2) / view["scale"],
        )

    view_script = "() => ({...window.edgeposMap.state.view})"
    before = page.evaluate(view_script)
    page.mouse.move(*cursor)
    for _ in range(2):  # exp(2 x 1500 x 0.0015) = 90 times closer
        page.mouse.wheel(0, -1500)
    page.wait_for_function(
        "([selector, width]) => document.querySelector(selector).getBoundingClientRect().width > width",
        arg=[ellipse, 10 * width],
    )
    after = page.evaluate(view_script)
    assert after["scale"] == pytest.approx(before["scale"] * math.exp(4.5), rel=1e-9)
    assert under_cursor(after) == pytest.approx(under_cursor(before), abs=1e-6)
    x, y = _centre(page, ellipse)
    assert x == pytest.approx(
        stage["x"] + stage["width"] / 2 + (last["x"] - after["cx"]) * after["scale"], abs=1.5
    )
    assert y == pytest.approx(
        stage["y"] + stage["height"] / 2 - (last["y"] - after["cy"]) * after["scale"], abs=1.5
    )
    RESULTS.mkdir(exist_ok=True)
    page.screenshot(path=str(RESULTS / "map.png"))

    # the guard does see outside requests (a page without the map's policy tries one), and the map made none
    probe = context.new_page()
    with pytest.raises(sync_api.Error):
        probe.goto("http://192.0.2.1/")
    assert outside == ["http://192.0.2.1/"]
    assert errors == []


def test_map_keeps_up_with_twenty_vehicles_at_20_hz(browser, tmp_path: Path):
    """20 vehicles, 20 fixes/s each on the scenario's clock: the page takes every fix from one stream, ends with
    every marker on its vehicle's last fix, and draws a frame in well under a frame's time. Without a WGS-84
    origin the grid is in site metres; the key outlives a reload of the tab and not a log-out."""
    with running(
        serve_command(1), _server_environment(), tmp_path / "server.log", ready_timeout_s=300.0
    ) as url:
        context, page, outside, errors = _guarded_page(browser)
        try:
            page.goto(f"{url}/map")
            page.fill("#key", ADMIN_KEY)
            page.click("#login-button")
            page.wait_for_selector("body[data-stream='live']", timeout=WAIT_MS)
            result = _simulate(url, 20, 100, batch_epochs=2, realtime=True)
            for run in result.vehicles:
                last = run.fixes[-1]
                data = _wait_for_fix(page, run.vehicle_id, last.t)
                assert (float(data["x"]), float(data["y"])) == (last.x, last.y)
            counts = page.evaluate("({...window.edgeposMap.state.counts})")
            assert counts["fixes"] == sum(len(run.fixes) for run in result.vehicles)  # every fix, once
            assert counts["streams"] == 1  # never dropped as a slow consumer, never reconnected
            assert counts["frames"] > 0 and counts["drawMs"] / counts["frames"] < 16.0
            rate = counts["fixes"] / result.elapsed_s
            print(f"map, 20 vehicles: {counts}, {result.elapsed_s:.1f} s, {rate:.0f} fixes/s")  # pytest -s
            assert page.get_attribute("#grid", "data-kind") == "metres"
            assert page.locator("#grid line[data-kind='x']").count() >= 2
            page.reload()  # the key is the tab's: the map opens again without the form
            page.wait_for_selector("body[data-stream='live']", timeout=WAIT_MS)
            # and, the stream carrying only new fixes, draws the live sessions' last fixes read from the API
            for run in result.vehicles:
                data = _wait_for_fix(page, run.vehicle_id, run.fixes[-1].t)
                assert (float(data["x"]), float(data["y"])) == (run.fixes[-1].x, run.fixes[-1].y)
            assert page.evaluate("window.edgeposMap.state.counts.fixes") == 0
            page.click("#logout")
            page.wait_for_selector("#login-form")
            assert page.evaluate("sessionStorage.getItem('edgepos.adminKey')") is None
            assert outside == [] and errors == []
        finally:
            context.close()

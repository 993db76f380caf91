// edgepos operator map: the RSU registry and every vehicle's latest fix, drawn as SVG in the site frame.
// No library and no outside request: the page talks only to the server it came from. The admin key is
// kept in this tab's sessionStorage and sent only in the Authorization header (never in a URL).
// The fix stream is read with fetch() and parsed here, since EventSource cannot send that header.
// Fixes only update the state; drawing happens at most once per animation frame.
"use strict";
(function () {
  const KEY_STORAGE = "edgepos.adminKey";
  const CHI2_95_2DOF = 5.991464547107979; // the 95 % ellipse of a 2-D Gaussian
  const CHI2_95 = [3.841458820694124, 5.991464547107979, 7.814727903251178, 9.487729036781154,
    11.070497693516351, 12.591587243743977];
  const NIS_WINDOW_S = 60; // NIS history kept per vehicle (vehicle clock)
  const TRAIL_S = 20; // trail length (vehicle clock)
  const TRAIL_POINTS = 200;
  const REJECTED_KEPT = 40;
  const STALE_MS = 10000; // no fix for this long: drawn faded
  const FORGET_MS = 120000; // no fix for this long: removed
  const STATUS_PERIOD_MS = 1000;
  const PANEL_PERIOD_MS = 250;
  const SVG = "http://www.w3.org/2000/svg";
  // WGS-84, for the latitude/longitude grid on the site's tangent plane
  const WGS84_A = 6378137.0;
  const WGS84_F = 1 / 298.257223563;
  const WGS84_E2 = WGS84_F * (2 - WGS84_F);

  const $ = (id) => document.getElementById(id);
  const state = {
    key: null,
    running: false,
    abort: null,
    lastEventId: null,
    rsus: [],
    vehicles: new Map(), // vehicle_id -> vehicle
    origin: null,
    selected: null,
    view: { cx: 0, cy: 0, scale: 1 }, // centre (site m) and pixels per metre
    autoFit: true,
    gridKey: "",
    frameRequested: false,
    lastPanel: 0,
    panelDirty: false,
    panelTimer: null,
    timers: [],
    // what the page did since it opened the map: the browser test and bench/map_browser.py read these
    counts: { fixes: 0, streams: 0, frames: 0, drawMs: 0, drawMsMax: 0 }, // fixes: from the stream
  };

  // ---- the site frame and WGS-84 ------------------------------------------------------------------
  // The site frame is the east-north tangent plane at the origin; near it (a site of a few km) latitude
  // and longitude change linearly with north and east by the ellipsoid's radii of curvature there.
  function radii(origin) {
    const s = Math.sin(origin.latitude);
    const w = Math.sqrt(1 - WGS84_E2 * s * s);
    const n = WGS84_A / w; // prime vertical
    const m = (WGS84_A * (1 - WGS84_E2)) / (w * w * w); // meridian
    return { north: m + origin.height, east: (n + origin.height) * Math.cos(origin.latitude) };
  }
  function siteToGeo(x, y, origin) {
    const r = radii(origin);
    return { latitude: origin.latitude + y / r.north, longitude: origin.longitude + x / r.east };
  }
  function geoToSite(latitude, longitude, origin) {
    const r = radii(origin);
    return { x: (longitude - origin.longitude) * r.east, y: (latitude - origin.latitude) * r.north };
  }

  // 95 % ellipse of a 2x2 covariance: semi-axes (m) and the major axis' angle (rad, CCW from east)
  function ellipse95(cov) {
    const a = cov[0][0], b = 0.5 * (cov[0][1] + cov[1][0]), c = cov[1][1];
    const mid = 0.5 * (a + c), half = Math.hypot(0.5 * (a - c), b);
    const k = Math.sqrt(CHI2_95_2DOF);
    return {
      major: k * Math.sqrt(Math.max(mid + half, 0)),
      minor: k * Math.sqrt(Math.max(mid - half, 0)),
      angle: 0.5 * Math.atan2(2 * b, a - c),
    };
  }
  function chi2Gate(dof) {
    if (dof >= 1 && dof <= CHI2_95.length) return CHI2_95[dof - 1];
    const h = 2 / (9 * dof); // Wilson-Hilferty
    return dof * Math.pow(1 - h + 1.6448536269514722 * Math.sqrt(h), 3);
  }

  // ---- requests -------------------------------------------------------------------------------------
  function headers(key) {
    return { Authorization: "Bearer " + key, Accept: "application/json" };
  }
  async function errorMessage(response) {
    try {
      const body = await response.json();
      if (body && body.error && body.error.message) return body.error.message;
    } catch (e) { /* not JSON */ }
    return "HTTP " + response.status;
  }
  async function api(path) {
    const response = await fetch(path, { headers: headers(state.key), cache: "no-store" });
    if (response.status === 401 || response.status === 403) {
      logout("The server refused the key: " + (await errorMessage(response)));
      throw new Error("refused");
    }
    if (!response.ok) throw new Error(path + ": " + (await errorMessage(response)));
    return response.json();
  }

  // ---- login ----------------------------------------------------------------------------------------
  async function login(key) {
    let response;
    try {
      response = await fetch("/v1/status", { headers: headers(key), cache: "no-store" });
    } catch (error) {
      return "The server does not answer: " + error.message;
    }
    if (response.status === 200) {
      sessionStorage.setItem(KEY_STORAGE, key);
      start(key, await response.json());
      return null;
    }
    const message = await errorMessage(response);
    if (response.status === 401 || response.status === 403) return "Refused: " + message;
    return "The server answered " + response.status + ": " + message;
  }
  function showLogin(message) {
    document.body.dataset.state = "login";
    $("app").hidden = true;
    $("login").hidden = false;
    $("key").value = "";
    $("login-error").hidden = !message;
    $("login-error").textContent = message || "";
  }
  function logout(message) {
    state.running = false;
    if (state.abort) state.abort.abort();
    state.timers.forEach(clearInterval);
    state.timers = [];
    sessionStorage.removeItem(KEY_STORAGE);
    state.key = null;
    state.vehicles.clear();
    state.selected = null;
    for (const id of ["vehicles", "trails", "rsus", "grid"]) $(id).replaceChildren();
    $("panel").hidden = true;
    showLogin(message);
  }

  function start(key, status) {
    state.key = key;
    state.running = true;
    state.lastEventId = null;
    state.autoFit = true;
    document.body.dataset.state = "map";
    $("login").hidden = true;
    $("app").hidden = false;
    showStatus(status);
    loadRsus();
    seedSessions().finally(() => streamLoop());
    state.timers.push(setInterval(pollStatus, STATUS_PERIOD_MS));
    state.timers.push(setInterval(forgetOld, 1000));
    requestDraw();
  }

  // ---- status, RSUs, sessions --------------------------------------------------------------------------
  function showStatus(s) {
    state.origin = s.origin;
    $("stat-sessions").textContent = String(s.sessions);
    $("stat-epochs").textContent = s.epochs_per_s.toFixed(1);
    $("stat-batches").textContent = s.batches_per_s.toFixed(1);
    $("stat-p99").textContent = s.batch_latency_p99_s === null ? "-" : (1000 * s.batch_latency_p99_s).toFixed(1) + " ms";
    $("stat-note").textContent = "over " + s.window_s + " s, worker that answered";
    for (const [name, value] of Object.entries(s)) {
      if (typeof value === "number") $("header").dataset[camel(name)] = String(value);
    }
  }
  function camel(name) {
    return name.replace(/_([a-z0-9])/g, (_, c) => c.toUpperCase());
  }
  async function pollStatus() {
    if (!state.running) return;
    try {
      showStatus(await api("/v1/status"));
    } catch (e) { /* shown by the stream state; retried next period */ }
  }
  async function loadRsus() {
    try {
      state.rsus = (await api("/v1/rsus")).rsus;
      state.gridKey = "";
      requestDraw();
    } catch (e) { /* an empty registry is drawn */ }
  }
  // The stream carries fixes from the moment it opens: the live sessions' latest fixes come first.
  async function seedSessions() {
    try {
      const list = await api("/v1/sessions?limit=1000");
      const ids = list.sessions.filter((s) => s.last_fix_t !== null).map((s) => s.session_id).slice(0, 200);
      for (let i = 0; i < ids.length; i += 10) {
        const sessions = await Promise.all(ids.slice(i, i + 10).map((id) => api("/v1/sessions/" + encodeURIComponent(id)).catch(() => null)));
        for (const s of sessions) {
          if (s && s.last_fix) onFix({ session_id: s.session_id, vehicle_id: s.vehicle_id, pipeline: s.pipeline, fix: s.last_fix });
        }
      }
    } catch (e) { /* the stream fills the map */ }
  }
  function forgetOld() {
    const now = performance.now();
    for (const [id, v] of state.vehicles) {
      if (now - v.seen > FORGET_MS) {
        v.group.remove();
        v.trail.remove();
        state.vehicles.delete(id);
        if (state.selected === id) closePanel();
      }
    }
    requestDraw();
  }

  // ---- the fix stream -----------------------------------------------------------------------------------
  function setStreamState(text) {
    $("stream-state").textContent = text;
    document.body.dataset.stream = text;
  }
  async function streamLoop() {
    while (state.running) {
      const controller = new AbortController();
      state.abort = controller;
      try {
        const h = headers(state.key);
        h.Accept = "text/event-stream";
        if (state.lastEventId) h["Last-Event-ID"] = state.lastEventId;
        const response = await fetch("/v1/stream/fixes", { headers: h, signal: controller.signal, cache: "no-store" });
        if (response.status === 401 || response.status === 403) {
          logout("The server refused the key: " + (await errorMessage(response)));
          return;
        }
        if (!response.ok) throw new Error(await errorMessage(response));
        state.counts.streams++;
        setStreamState("live");
        const reader = response.body.getReader();
        const decoder = new TextDecoder();
        let buffer = "";
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buffer = parseEvents(buffer + decoder.decode(value, { stream: true }).replace(/\r\n?/g, "\n"));
        }
      } catch (error) {
        if (!state.running) return;
      }
      if (!state.running) return;
      setStreamState("reconnecting");
      await new Promise((resolve) => setTimeout(resolve, 1000));
    }
  }
  // Server-sent events: blocks separated by a blank line, "field: value" lines, ":" comments.
  function parseEvents(buffer) {
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let event = "message", data = [], id = null;
      for (const line of block.split("\n")) {
        if (!line || line[0] === ":") continue;
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        let value = colon < 0 ? "" : line.slice(colon + 1);
        if (value[0] === " ") value = value.slice(1);
        if (field === "event") event = value;
        else if (field === "data") data.push(value);
        else if (field === "id") id = value;
      }
      if (id !== null) state.lastEventId = id;
      if (event === "fix" && data.length) {
        state.counts.fixes++;
        onFix(JSON.parse(data.join("\n")));
      }
      else if (event === "missed") setStreamState("live (some fixes missed)");
    }
    return buffer;
  }

  function onFix(event) {
    const fix = event.fix;
    let v = state.vehicles.get(event.vehicle_id);
    if (!v || v.sessionId !== event.session_id) {
      if (v) { v.group.remove(); v.trail.remove(); }
      v = newVehicle(event);
      state.vehicles.set(event.vehicle_id, v);
    }
    v.seen = performance.now();
    if (v.fix === null || fix.t >= v.fix.t) {
      v.fix = fix;
      if (fix.x !== null && fix.y !== null) v.positioned = fix;
    }
    if (fix.x !== null && fix.y !== null) {
      const i = v.points.findIndex((p) => p[2] === fix.t);
      if (i >= 0) v.points[i] = [fix.x, fix.y, fix.t]; // a revised fix replaces its epoch's
      else v.points.push([fix.x, fix.y, fix.t]);
      const newest = v.positioned ? v.positioned.t : fix.t;
      while (v.points.length > TRAIL_POINTS || (v.points.length && v.points[0][2] < newest - TRAIL_S)) v.points.shift();
    }
    if (fix.nis !== null) {
      v.nis.push([fix.t, fix.nis, fix.nis_dof]);
      const newest = v.fix.t;
      while (v.nis.length && v.nis[0][0] < newest - NIS_WINDOW_S) v.nis.shift();
    }
    for (const m of fix.measurements) {
      if (!m.used) v.rejected.push({ t: fix.t, type: m.type, index: m.index, reason: m.reason || "not used" });
      else if (m.doppler_used === false) v.rejected.push({ t: fix.t, type: m.type + " Doppler", index: m.index, reason: m.doppler_reason || "not used" });
    }
    if (v.rejected.length > REJECTED_KEPT) v.rejected.splice(0, v.rejected.length - REJECTED_KEPT);
    v.dirty = true;
    if (state.selected === event.vehicle_id) state.panelDirty = true;
    requestDraw();
  }

  function svg(tag, attributes, parent) {
    const element = document.createElementNS(SVG, tag);
    for (const [name, value] of Object.entries(attributes || {})) element.setAttribute(name, value);
    if (parent) parent.appendChild(element);
    return element;
  }
  function newVehicle(event) {
    const group = svg("g", { class: "vehicle" }, $("vehicles"));
    group.dataset.vehicleId = event.vehicle_id;
    group.dataset.sessionId = event.session_id;
    group.dataset.pipeline = event.pipeline;
    const v = {
      vehicleId: event.vehicle_id, sessionId: event.session_id, pipeline: event.pipeline,
      fix: null, positioned: null, points: [], nis: [], rejected: [], seen: 0, dirty: true,
      group,
      trail: svg("polyline", { class: "trail" }, $("trails")),
      ellipse: svg("ellipse", { class: "ellipse" }, group),
      arrow: svg("path", { class: "body", d: "M 10 0 L -6 6 L -3 0 L -6 -6 Z" }, group),
      dot: svg("circle", { class: "body", r: 5 }, group),
      label: svg("text", { class: "label", dx: 9, dy: -8 }, group),
      session: null,
    };
    v.label.textContent = event.vehicle_id;
    group.addEventListener("click", (e) => { e.stopPropagation(); if (!dragMoved) select(event.vehicle_id); });
    return v;
  }

  // ---- drawing --------------------------------------------------------------------------------------------
  function requestDraw() {
    if (state.frameRequested) return;
    state.frameRequested = true;
    requestAnimationFrame(draw);
  }
  function size() {
    const box = $("map").getBoundingClientRect();
    return { w: Math.max(box.width, 1), h: Math.max(box.height, 1) };
  }
  function toScreen(x, y, s) {
    const v = state.view;
    return [s.w / 2 + (x - v.cx) * v.scale, s.h / 2 - (y - v.cy) * v.scale];
  }
  function fitView(s) {
    const xs = [], ys = [];
    for (const r of state.rsus) { xs.push(r.x); ys.push(r.y); }
    for (const v of state.vehicles.values()) if (v.positioned) { xs.push(v.positioned.x); ys.push(v.positioned.y); }
    if (!xs.length) { xs.push(-50, 50); ys.push(-50, 50); }
    const minX = Math.min(...xs), maxX = Math.max(...xs), minY = Math.min(...ys), maxY = Math.max(...ys);
    const spanX = Math.max(maxX - minX, 20), spanY = Math.max(maxY - minY, 20);
    const scale = 0.85 * Math.min(s.w / spanX, s.h / spanY);
    const view = { cx: (minX + maxX) / 2, cy: (minY + maxY) / 2, scale };
    // refit only when the content leaves the view or takes less than half of it: no jitter at 20 Hz
    const v = state.view;
    const inside = xs.every((x, i) => {
      const [px, py] = toScreen(x, ys[i], s);
      return px > 10 && px < s.w - 10 && py > 10 && py < s.h - 10;
    });
    if (!inside || v.scale > 1.6 * scale || v.scale < 0.5 * scale || state.gridKey === "") state.view = view;
  }
  function niceStep(raw) {
    const power = Math.pow(10, Math.floor(Math.log10(raw)));
    for (const f of [1, 2, 5, 10]) if (f * power >= raw) return Number((f * power).toPrecision(1));
    return Number((10 * power).toPrecision(1));
  }
  function drawGrid(s) {
    const grid = $("grid");
    grid.replaceChildren();
    const v = state.view;
    const x0 = v.cx - s.w / 2 / v.scale, x1 = v.cx + s.w / 2 / v.scale;
    const y0 = v.cy - s.h / 2 / v.scale, y1 = v.cy + s.h / 2 / v.scale;
    const line = (ax, ay, bx, by, text, kind, value) => {
      const [pax, pay] = toScreen(ax, ay, s), [pbx, pby] = toScreen(bx, by, s);
      const l = svg("line", { class: "grid-line", x1: pax, y1: pay, x2: pbx, y2: pby }, grid);
      l.dataset.kind = kind;
      l.dataset.value = String(value);
      const vertical = kind === "x" || kind === "longitude";
      const t = svg("text", { class: "grid-label", x: vertical ? pax + 3 : 3, y: vertical ? 12 : pay - 3 }, grid);
      t.textContent = text;
    };
    const o = state.origin;
    grid.dataset.kind = o ? "wgs84" : "metres";
    if (o) {
      const r = radii(o);
      const stepDeg = niceStep((90 / v.scale) / r.north * 180 / Math.PI); // about 90 px apart
      const lat0 = (o.latitude + y0 / r.north) * 180 / Math.PI, lat1 = (o.latitude + y1 / r.north) * 180 / Math.PI;
      const lon0 = (o.longitude + x0 / r.east) * 180 / Math.PI, lon1 = (o.longitude + x1 / r.east) * 180 / Math.PI;
      const decimals = Math.max(0, -Math.floor(Math.log10(stepDeg)) + 1);
      for (let k = Math.ceil(lat0 / stepDeg); k * stepDeg <= lat1 && k - Math.ceil(lat0 / stepDeg) < 200; k++) {
        const deg = k * stepDeg, y = geoToSite(deg * Math.PI / 180, o.longitude, o).y;
        line(x0, y, x1, y, deg.toFixed(decimals) + "°", "latitude", deg);
      }
      for (let k = Math.ceil(lon0 / stepDeg); k * stepDeg <= lon1 && k - Math.ceil(lon0 / stepDeg) < 200; k++) {
        const deg = k * stepDeg, x = geoToSite(o.latitude, deg * Math.PI / 180, o).x;
        line(x, y0, x, y1, deg.toFixed(decimals) + "°", "longitude", deg);
      }
      $("scale-note").textContent = "grid " + stepDeg.toFixed(Math.max(0, decimals - 1)) + "° (WGS-84 on the site's tangent plane)";
    } else {
      const step = niceStep(90 / v.scale);
      const decimals = Math.max(0, -Math.floor(Math.log10(step)));
      for (let k = Math.ceil(x0 / step); k * step <= x1; k++) line(k * step, y0, k * step, y1, (k * step).toFixed(decimals) + " m", "x", k * step);
      for (let k = Math.ceil(y0 / step); k * step <= y1; k++) line(x0, k * step, x1, k * step, (k * step).toFixed(decimals) + " m", "y", k * step);
      $("scale-note").textContent = "grid " + step + " m (site frame: x east, y north)";
    }
  }
  function drawRsus(s) {
    const layer = $("rsus");
    layer.replaceChildren();
    for (const r of state.rsus) {
      const [px, py] = toScreen(r.x, r.y, s);
      if (r.radius) svg("circle", { class: "rsu-range", cx: px, cy: py, r: r.radius * state.view.scale }, layer);
      const mark = svg("rect", { class: "rsu", x: px - 5, y: py - 5, width: 10, height: 10 }, layer);
      mark.dataset.rsuId = r.id;
      mark.dataset.x = String(r.x);
      mark.dataset.y = String(r.y);
      const label = svg("text", { class: "rsu-label", x: px + 8, y: py + 14 }, layer);
      label.textContent = r.id;
    }
  }
  function drawVehicle(v, s, now) {
    const fix = v.positioned, latest = v.fix, g = v.group;
    const status = latest ? latest.status : "uninitialised";
    g.setAttribute("class", "vehicle status-" + status + (now - v.seen > STALE_MS ? " stale" : "") + (state.selected === v.vehicleId ? " selected" : ""));
    g.dataset.status = status;
    v.trail.setAttribute("class", "trail status-" + status + (now - v.seen > STALE_MS ? " stale" : ""));
    if (!fix) { g.setAttribute("visibility", "hidden"); return; }
    g.removeAttribute("visibility");
    const [px, py] = toScreen(fix.x, fix.y, s);
    g.setAttribute("transform", "translate(" + px.toFixed(2) + " " + py.toFixed(2) + ")");
    g.dataset.x = String(fix.x);
    g.dataset.y = String(fix.y);
    g.dataset.t = String(fix.t);
    g.dataset.heading = fix.heading === null ? "" : String(fix.heading);
    if (fix.heading !== null) {
      v.arrow.removeAttribute("visibility");
      v.dot.setAttribute("visibility", "hidden");
      v.arrow.setAttribute("transform", "rotate(" + (-fix.heading * 180 / Math.PI).toFixed(2) + ")");
    } else {
      v.arrow.setAttribute("visibility", "hidden");
      v.dot.removeAttribute("visibility");
    }
    if (fix.position_covariance) {
      const e = ellipse95(fix.position_covariance);
      g.dataset.ellipseMajor = String(e.major);
      g.dataset.ellipseMinor = String(e.minor);
      g.dataset.ellipseAngle = String(e.angle);
      v.ellipse.setAttribute("rx", Math.max(e.major * state.view.scale, 0.5).toFixed(2));
      v.ellipse.setAttribute("ry", Math.max(e.minor * state.view.scale, 0.5).toFixed(2));
      v.ellipse.setAttribute("transform", "rotate(" + (-e.angle * 180 / Math.PI).toFixed(2) + ")");
      v.ellipse.removeAttribute("visibility");
    } else {
      v.ellipse.setAttribute("visibility", "hidden");
    }
    v.trail.setAttribute("points", v.points.map((p) => toScreen(p[0], p[1], s).map((c) => c.toFixed(1)).join(",")).join(" "));
    v.trail.dataset.points = String(v.points.length);
  }
  function draw() {
    state.frameRequested = false;
    if (!state.running) return;
    const started = performance.now();
    drawFrame();
    const ms = performance.now() - started;
    state.counts.frames++;
    state.counts.drawMs += ms;
    state.counts.drawMsMax = Math.max(state.counts.drawMsMax, ms);
  }
  function drawFrame() {
    const s = size();
    if (state.autoFit) fitView(s);
    const key = [s.w, s.h, state.view.cx, state.view.cy, state.view.scale, state.rsus.length, JSON.stringify(state.origin)].join("|");
    const viewChanged = key !== state.gridKey;
    if (viewChanged) {
      state.gridKey = key;
      drawGrid(s);
      drawRsus(s);
    }
    const now = performance.now();
    for (const v of state.vehicles.values()) {
      if (v.dirty || viewChanged || now - v.seen > STALE_MS) { drawVehicle(v, s, now); v.dirty = false; }
    }
    $("stat-vehicles").textContent = String(state.vehicles.size);
    if (state.selected && state.panelDirty) {
      if (now - state.lastPanel >= PANEL_PERIOD_MS) {
        state.lastPanel = now;
        state.panelDirty = false;
        drawPanel();
      } else if (!state.panelTimer) {
        state.panelTimer = setTimeout(() => { state.panelTimer = null; requestDraw(); }, PANEL_PERIOD_MS);
      }
    }
  }

  // ---- the detail panel -------------------------------------------------------------------------------------
  function select(vehicleId) {
    state.selected = vehicleId;
    const v = state.vehicles.get(vehicleId);
    $("panel").hidden = false;
    $("panel").dataset.vehicleId = vehicleId;
    v.session = null;
    api("/v1/sessions/" + encodeURIComponent(v.sessionId)).then((s) => { v.session = s; state.lastPanel = 0; state.panelDirty = true; requestDraw(); }).catch(() => {});
    state.lastPanel = 0;
    state.panelDirty = true;
    for (const other of state.vehicles.values()) other.dirty = true;
    requestDraw();
  }
  function closePanel() {
    state.selected = null;
    $("panel").hidden = true;
    for (const v of state.vehicles.values()) v.dirty = true;
    requestDraw();
  }
  function facts(list, pairs) {
    list.replaceChildren();
    for (const [name, value] of pairs) {
      const dt = document.createElement("dt"), dd = document.createElement("dd");
      dt.textContent = name;
      dd.textContent = value;
      list.append(dt, dd);
    }
  }
  const num = (value, digits, unit) => (value === null || value === undefined ? "-" : value.toFixed(digits) + (unit ? " " + unit : ""));
  function drawPanel() {
    const v = state.vehicles.get(state.selected);
    if (!v || !v.fix) return;
    const fix = v.fix, p = v.positioned;
    $("panel-title").textContent = v.vehicleId;
    const e = p && p.position_covariance ? ellipse95(p.position_covariance) : null;
    const pairs = [
      ["pipeline", v.pipeline],
      ["status", fix.status + (fix.divergence ? " (" + fix.divergence + ")" : "")],
      ["t", num(fix.t, 2, "s")],
      ["x, y", p ? num(p.x, 2) + ", " + num(p.y, 2) + " m" : "-"],
      ["speed", num(p && p.speed, 2, "m/s")],
      ["heading", p && p.heading !== null ? (p.heading * 180 / Math.PI).toFixed(1) + "° (CCW from east)" : "-"],
      ["95 % ellipse", e ? e.major.toFixed(2) + " × " + e.minor.toFixed(2) + " m" : "-"],
    ];
    if (p && p.latitude !== null && p.latitude !== undefined) {
      pairs.push(["lat, lon", (p.latitude * 180 / Math.PI).toFixed(7) + "°, " + (p.longitude * 180 / Math.PI).toFixed(7) + "°"]);
    }
    pairs.push(["session", v.sessionId]);
    facts($("panel-facts"), pairs);
    drawNis(v);
    const models = $("models");
    models.replaceChildren();
    for (const [name, probability] of Object.entries(fix.model_probabilities)) {
      const row = document.createElement("div");
      row.className = "model";
      row.dataset.model = name;
      row.dataset.probability = String(probability);
      const label = document.createElement("span"), track = document.createElement("span"), bar = document.createElement("div"), value = document.createElement("span");
      label.textContent = name;
      bar.className = "bar";
      bar.style.width = (100 * probability).toFixed(1) + "%";
      track.append(bar);
      value.textContent = probability.toFixed(3);
      row.append(label, track, value);
      models.append(row);
    }
    const rejected = $("rejected");
    rejected.replaceChildren();
    for (const r of v.rejected.slice().reverse()) {
      const li = document.createElement("li");
      li.textContent = "t " + r.t.toFixed(2) + " s, " + r.type + " #" + r.index + ": " + r.reason;
      li.dataset.type = r.type;
      rejected.append(li);
    }
    if (!v.rejected.length) {
      const li = document.createElement("li");
      li.className = "note";
      li.textContent = "none since the map opened";
      rejected.append(li);
    }
    const s = v.session;
    facts($("session-facts"), s ? [
      ["batches", String(s.batches)], ["epochs", String(s.epochs)], ["last seq", String(s.last_seq)],
      ...Object.entries(s.options).map(([k, value]) => [k, JSON.stringify(value)]),
    ] : [["", "reading..."]]);
  }
  function drawNis(v) {
    const plot = $("nis-plot");
    plot.replaceChildren();
    const w = 300, h = 90, pad = 4;
    const points = v.nis;
    plot.dataset.points = String(points.length);
    if (!points.length) {
      $("nis-summary").textContent = "no update in the last 60 s";
      return;
    }
    // the last minute, or since the first update when that is shorter (a young session fills the plot)
    const tEnd = points[points.length - 1][0], span = Math.max(tEnd - points[0][0], 1);
    const tStart = tEnd - span;
    const top = Math.max(...points.map((p) => Math.max(p[1], chi2Gate(p[2])))) * 1.1;
    const px = (t) => pad + ((t - tStart) / span) * (w - 2 * pad);
    const py = (value) => h - pad - (value / top) * (h - 2 * pad);
    svg("polyline", { class: "gate", points: points.map((p) => px(p[0]).toFixed(1) + "," + py(chi2Gate(p[2])).toFixed(1)).join(" ") }, plot);
    svg("polyline", { class: "nis", points: points.map((p) => px(p[0]).toFixed(1) + "," + py(p[1]).toFixed(1)).join(" ") }, plot);
    svg("text", { x: 4, y: 11 }, plot).textContent = top.toFixed(1);
    const meanNis = points.reduce((a, p) => a + p[1], 0) / points.length;
    const meanDof = points.reduce((a, p) => a + p[2], 0) / points.length;
    const over = points.filter((p) => p[1] > chi2Gate(p[2])).length;
    $("nis-summary").textContent = "over " + span.toFixed(1) + " s: mean NIS " + meanNis.toFixed(2) + " for mean dof " + meanDof.toFixed(2) + "; " +
      over + " of " + points.length + " updates above the 95 % chi-square bound (dashed)";
  }

  // ---- pan and zoom ------------------------------------------------------------------------------------------
  let drag = null, dragMoved = false;
  function setupInteraction() {
    const map = $("map");
    map.addEventListener("wheel", (e) => {
      e.preventDefault();
      const s = size(), box = map.getBoundingClientRect();
      const mx = e.clientX - box.left, my = e.clientY - box.top, v = state.view;
      const x = v.cx + (mx - s.w / 2) / v.scale, y = v.cy - (my - s.h / 2) / v.scale;
      v.scale *= Math.exp(-e.deltaY * 0.0015);
      v.cx = x - (mx - s.w / 2) / v.scale;
      v.cy = y + (my - s.h / 2) / v.scale;
      state.autoFit = false;
      requestDraw();
    }, { passive: false });
    map.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, cx: state.view.cx, cy: state.view.cy };
      dragMoved = false;
    });
    window.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      if (!dragMoved && Math.hypot(dx, dy) < 4) return;
      dragMoved = true;
      map.classList.add("dragging");
      state.autoFit = false;
      state.view.cx = drag.cx - dx / state.view.scale;
      state.view.cy = drag.cy + dy / state.view.scale;
      requestDraw();
    });
    window.addEventListener("pointerup", () => { drag = null; map.classList.remove("dragging"); });
    window.addEventListener("resize", requestDraw);
    $("fit").addEventListener("click", () => { state.autoFit = true; state.gridKey = ""; requestDraw(); });
    $("logout").addEventListener("click", () => logout(""));
    $("panel-close").addEventListener("click", closePanel);
    $("login-form").addEventListener("submit", async (e) => {
      e.preventDefault();
      const key = $("key").value.trim();
      $("login-button").disabled = true;
      const refusal = await login(key);
      $("login-button").disabled = false;
      if (refusal !== null) showLogin(refusal);
    });
  }

  window.edgeposMap = { siteToGeo, geoToSite, ellipse95, chi2Gate, state };
  setupInteraction();
  const saved = sessionStorage.getItem(KEY_STORAGE);
  if (saved) {
    login(saved).then((refusal) => { if (refusal !== null) { sessionStorage.removeItem(KEY_STORAGE); showLogin(refusal); } });
  } else {
    showLogin("");
  }
})();

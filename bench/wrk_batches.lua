-- wrk script of bench/wrk_load.py: one simulated vehicle per wrk thread (one connection each).
--
-- Each vehicle opens a session (admin key), then sends the pre-built batches of batches.jsonl in
-- order with seq 1, 2, ...; when they run out it opens a new session (which supersedes the old one,
-- as a vehicle starting a new trip does) and starts again. Every answer's status is counted per
-- thread; done() prints one line "WRK_RESULT {json}" with the totals for the Python side.
--
-- Arguments (after wrk's "--"): data directory, admin key.

local threads = {}
local next_vehicle = 0

function setup(thread)
  next_vehicle = next_vehicle + 1
  thread:set("vehicle", next_vehicle)
  table.insert(threads, thread)
end

function init(args)
  local directory, admin_key = args[1], args[2]
  bodies = {}
  for line in io.lines(directory .. "/batches.jsonl") do
    table.insert(bodies, line)
  end
  local template = io.open(directory .. "/create.json"):read("*a")
  create_body = string.gsub(template, "VEHICLE", tostring(vehicle))
  admin_headers = {["Authorization"] = "Bearer " .. admin_key, ["Content-Type"] = "application/json"}
  batch_headers = nil
  batch_path = nil
  position = 0
  opening = false
  batches_ok, epochs_ok, errors, trips = 0, 0, 0, 0
  epochs_per_batch = {}
  for index, body in ipairs(bodies) do
    local epochs, last = 0, nil
    for t in string.gmatch(body, '"t":([%d%.eE+-]+)') do
      if t ~= last then epochs = epochs + 1; last = t end
    end
    epochs_per_batch[index] = epochs
  end
end

function request()
  if batch_path == nil or position >= #bodies then
    opening = true
    return wrk.format("POST", "/v1/sessions", admin_headers, create_body)
  end
  position = position + 1
  local body = string.gsub(bodies[position], '"seq":0', '"seq":' .. position, 1)
  return wrk.format("POST", batch_path, batch_headers, body)
end

function response(status, headers, body)
  if opening then
    opening = false
    if status == 201 then
      local session_id = string.match(body, '"session_id":"([^"]+)"')
      local token = string.match(body, '"token":"([^"]+)"')
      batch_path = "/v1/sessions/" .. session_id .. "/batches"
      batch_headers = {["Authorization"] = "Bearer " .. token, ["Content-Type"] = "application/json"}
      position = 0
      trips = trips + 1
    else
      errors = errors + 1
    end
  elseif status == 200 then
    batches_ok = batches_ok + 1
    epochs_ok = epochs_ok + epochs_per_batch[position]
  else
    errors = errors + 1
    batch_path = nil -- start a new trip: the session's seq may no longer follow
  end
end

function done(summary, latency, requests)
  local batches, epochs, failed, opened = 0, 0, 0, 0
  for _, thread in ipairs(threads) do
    batches = batches + thread:get("batches_ok")
    epochs = epochs + thread:get("epochs_ok")
    failed = failed + thread:get("errors")
    opened = opened + thread:get("trips")
  end
  io.write(string.format(
    'WRK_RESULT {"batches": %d, "epochs": %d, "errors": %d, "trips": %d, "requests": %d, ' ..
    '"duration_us": %d, "socket_errors": %d, "p50_us": %d, "p90_us": %d, "p99_us": %d}\n',
    batches, epochs, failed, opened, summary.requests, summary.duration,
    summary.errors.connect + summary.errors.read + summary.errors.write + summary.errors.timeout,
    latency:percentile(50), latency:percentile(90), latency:percentile(99)))
end

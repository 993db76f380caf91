"""The Lua scripts of the Redis store (``store.redis``): every write that touches more than one key is
one script, so that Redis applies it atomically whichever worker sends it. Each script's comment gives
its KEYS and ARGV; the arithmetic of TAKE_REQUEST is ``store.ratelimit.gcra``, transcribed."""

from __future__ import annotations

# Remove index entries scored below ARGV[1] (exclusive) and their session hashes (prefix ARGV[2]).
# Live-session pointers are not touched here (an expired session's hash may already be gone, so its
# vehicle is unknown): every reader treats a pointer to a missing or expired session as absent, and a
# pointer carries its session's TTL (set by create, refreshed by each compare-and-set), so it goes by
# itself.
PURGE = """
local function purge(index, cutoff, prefix)
  local stale = redis.call('ZRANGEBYSCORE', index, '-inf', '(' .. cutoff)
  for _, sid in ipairs(stale) do
    redis.call('DEL', prefix .. sid)
  end
  if #stale > 0 then
    redis.call('ZREMRANGEBYSCORE', index, '-inf', '(' .. cutoff)
  end
  return #stale
end
"""

# KEYS: session hash, index, vehicles, the vehicle's live pointer, the vehicle's track.
# ARGV: cutoff, session-key prefix, limit, ttl ms, score, id, vehicle id, key hash ('' = no registry
# check), supersession-key prefix, now, fields...
# Returns {1, superseded id or ''}, or {-1} (id taken), {-2} (too many sessions), {-3} (the vehicle is
# not registered with this key). Nothing is written unless it returns 1.
CREATE = (
    PURGE
    + """
if ARGV[8] ~= '' then
  local vehicle = redis.call('HGET', KEYS[3], ARGV[7])
  if (not vehicle) or cjson.decode(vehicle)[1] ~= ARGV[8] then return {-3} end
end
purge(KEYS[2], ARGV[1], ARGV[2])
if redis.call('EXISTS', KEYS[1]) == 1 then return {-1} end
local old = redis.call('GET', KEYS[4])
local old_token = false
if old then
  -- after the purge an existing session hash is a live session
  old_token = redis.call('HGET', ARGV[2] .. old, 'token_hash')
  if not old_token then
    redis.call('ZREM', KEYS[2], old)
    old = false
  end
end
local live = redis.call('ZCARD', KEYS[2])
if old then live = live - 1 end  -- the superseded session makes room for its successor
if live >= tonumber(ARGV[3]) then return {-2} end
if old then
  redis.call('DEL', ARGV[2] .. old)
  redis.call('ZREM', KEYS[2], old)
  local superseded = ARGV[9] .. old
  redis.call('DEL', superseded)
  redis.call('HSET', superseded, 'superseded_by', ARGV[6], 'token_hash', old_token, 'at', ARGV[10])
  redis.call('PEXPIRE', superseded, ARGV[4])
end
redis.call('DEL', KEYS[5])
redis.call('HSET', KEYS[1], unpack(ARGV, 11))
redis.call('PEXPIRE', KEYS[1], ARGV[4])
redis.call('ZADD', KEYS[2], ARGV[5], ARGV[6])
redis.call('SET', KEYS[4], ARGV[6], 'PX', ARGV[4])
return {1, old or ''}
"""
)

# KEYS: session hash, index, the vehicle's live pointer, the staged hash and, when the batch was computed on a
# worker's cached RSU map, the map's token. ARGV: expected version, ttl ms, score, id, and that cached map's
# token. The new record arrives as the staged hash, written by a plain HSET just before this script in
# the same pipeline; the script moves it in place of the session's (RENAME: no copy) only if the version is
# still the expected one, else drops it. The state and the stored answer (some 50 kB for a 20-epoch batch)
# never pass through Lua, whose argument handling costs Redis about 1.6 ns per byte: twice the CPU of the
# whole write (bench/redis_ops.py). Returns 1 if applied, 0 if the version moved (or the session is gone:
# deleted, superseded, revoked, expired), -1 if the staged hash is missing (its HSET failed: nothing
# written), -2 if the RSU map changed since the worker cached it (nothing written).
_COMPARE_AND_RENAME_BODY = """
if redis.call('EXISTS', KEYS[4]) == 0 then return -1 end
local version = redis.call('HGET', KEYS[1], 'version')
if (not version) or version ~= ARGV[1] then
  redis.call('DEL', KEYS[4])
  return 0
end
if token_key and (redis.call('GET', token_key) or '') ~= ARGV[5] then
  redis.call('DEL', KEYS[4])
  return -2
end
redis.call('RENAME', KEYS[4], KEYS[1])
redis.call('PEXPIRE', KEYS[1], ARGV[2])
redis.call('ZADD', KEYS[2], ARGV[3], ARGV[4])
if redis.call('GET', KEYS[3]) == ARGV[4] then redis.call('PEXPIRE', KEYS[3], ARGV[2]) end
"""
COMPARE_AND_RENAME = "local token_key = KEYS[5]" + _COMPARE_AND_RENAME_BODY + "return 1\n"

# KEYS: session hash, index. ARGV: id, live-pointer prefix, track prefix. Removes the session and,
# when the vehicle's pointer names it, the pointer and the vehicle's track. Returns 1 if it existed.
DELETE = """
local vehicle = redis.call('HGET', KEYS[1], 'vehicle_id')
local removed = redis.call('DEL', KEYS[1])
redis.call('ZREM', KEYS[2], ARGV[1])
if vehicle then
  local pointer = ARGV[2] .. vehicle
  if redis.call('GET', pointer) == ARGV[1] then
    redis.call('DEL', pointer)
    redis.call('DEL', ARGV[3] .. vehicle)
  end
end
return removed
"""

# KEYS: the vehicle's live pointer, the session hash, index, the vehicle's track. ARGV: session id,
# cutoff, track value, ttl ms. Writes the track only while that session is the vehicle's live one.
PUT_TRACK = """
if redis.call('GET', KEYS[1]) ~= ARGV[1] then return 0 end
if redis.call('EXISTS', KEYS[2]) == 0 then return 0 end
local score = redis.call('ZSCORE', KEYS[3], ARGV[1])
if (not score) or tonumber(score) < tonumber(ARGV[2]) then return 0 end
redis.call('SET', KEYS[4], ARGV[3], 'PX', ARGV[4])
return 1
"""

# KEYS: vehicles, vehicle keys. ARGV: (vehicle id, key hash, JSON value) triples. Adds the vehicles not
# registered yet; returns their ids, or {-1} (and writes nothing) when a key hash to add is already
# another vehicle's or appears twice.
ADD_VEHICLES = """
local fresh, ids, keys = {}, {}, {}
for i = 1, #ARGV, 3 do
  local vehicle, key = ARGV[i], ARGV[i + 1]
  if (not ids[vehicle]) and redis.call('HEXISTS', KEYS[1], vehicle) == 0 then
    if keys[key] or redis.call('HEXISTS', KEYS[2], key) == 1 then return {-1} end
    ids[vehicle], keys[key] = true, true
    fresh[#fresh + 1] = i
  end
end
local added = {}
for _, i in ipairs(fresh) do
  redis.call('HSET', KEYS[1], ARGV[i], ARGV[i + 2])
  redis.call('HSET', KEYS[2], ARGV[i + 1], ARGV[i])
  added[#added + 1] = ARGV[i]
end
return added
"""

# KEYS: vehicles, vehicle keys. ARGV: vehicle id, new key hash, now (repr). Returns the new JSON value,
# 0 when the vehicle is not registered, -1 when the key hash is another vehicle's. Numbers are
# rewritten with 17 significant digits, which round-trips a double exactly.
ROTATE_VEHICLE_KEY = """
local value = redis.call('HGET', KEYS[1], ARGV[1])
if not value then return 0 end
local owner = redis.call('HGET', KEYS[2], ARGV[2])
if owner and owner ~= ARGV[1] then return -1 end
local vehicle = cjson.decode(value)
if redis.call('HGET', KEYS[2], vehicle[1]) == ARGV[1] then redis.call('HDEL', KEYS[2], vehicle[1]) end
local rotated = '[' .. cjson.encode(ARGV[2]) .. ',' .. string.format('%.17g', vehicle[2]) .. ','
  .. ARGV[3] .. ']'
redis.call('HSET', KEYS[1], ARGV[1], rotated)
redis.call('HSET', KEYS[2], ARGV[2], ARGV[1])
return rotated
"""

# Revoking a vehicle, in two parts that a Redis Cluster runs as two single-slot scripts
# (store.redis_cluster) and one Redis as one script.
# deregister(vehicles, vehicle keys, vehicle id): removes the vehicle and its key's entry; false if it
# was not registered.
DEREGISTER_FN = """
local function deregister(vehicles, vehicle_keys, vehicle_id)
  local value = redis.call('HGET', vehicles, vehicle_id)
  if not value then return false end
  local key = cjson.decode(value)[1]
  redis.call('HDEL', vehicles, vehicle_id)
  if redis.call('HGET', vehicle_keys, key) == vehicle_id then redis.call('HDEL', vehicle_keys, key) end
  return true
end
"""

# end_live_session(live pointer, track, index, session-key prefix, cutoff): ends the vehicle's live
# session (hash, index entry, pointer) and deletes its track; returns the session's id when it was
# live, else ''.
END_LIVE_SESSION_FN = """
local function end_live_session(live, track, index, session_prefix, cutoff)
  local ended = ''
  local sid = redis.call('GET', live)
  if sid then
    local score = redis.call('ZSCORE', index, sid)
    local existed = redis.call('DEL', session_prefix .. sid)
    redis.call('ZREM', index, sid)
    if existed == 1 and score and tonumber(score) >= tonumber(cutoff) then ended = sid end
    redis.call('DEL', live)
  end
  redis.call('DEL', track)
  return ended
end
"""

# KEYS: vehicles, vehicle keys, the vehicle's live pointer, the vehicle's track, index. ARGV: vehicle
# id, session-key prefix, cutoff. Returns {0} when not registered, else {1, ended session id or ''}.
DELETE_VEHICLE = (
    DEREGISTER_FN
    + END_LIVE_SESSION_FN
    + """
if not deregister(KEYS[1], KEYS[2], ARGV[1]) then return {0} end
return {1, end_live_session(KEYS[3], KEYS[4], KEYS[5], ARGV[2], ARGV[3])}
"""
)

# KEYS: index. ARGV: cutoff, session-key prefix. Returns {purged, remaining}.
PURGE_AND_COUNT = (
    PURGE
    + """
local purged = purge(KEYS[1], ARGV[1], ARGV[2])
return {purged, redis.call('ZCARD', KEYS[1])}
"""
)

# GCRA (edgepos.store.ratelimit.gcra, transcribed). KEYS: the key's TAT. ARGV: now, interval,
# tolerance, slack (s). Returns the wait in seconds as a string ("0" when allowed, and the TAT is stored
# with a TTL until the key's whole burst is back).
TAKE_REQUEST = """
local now = tonumber(ARGV[1])
local tat = tonumber(redis.call('GET', KEYS[1]) or '')
if (not tat) or tat < now then tat = now end
local wait = tat - now - tonumber(ARGV[3])
if wait > tonumber(ARGV[4]) then return string.format('%.17g', wait) end
tat = tat + tonumber(ARGV[2])
redis.call('SET', KEYS[1], string.format('%.17g', tat), 'PX', math.ceil((tat - now) * 1000) + 1)
return '0'
"""

# Redis Cluster: DELETE_VEHICLE's two parts as scripts of their own (store.redis_cluster).
# KEYS: vehicles, vehicle keys (the registry's slot). ARGV: vehicle id. Returns 1 if it was registered.
DEREGISTER_VEHICLE = (
    DEREGISTER_FN
    + """
if deregister(KEYS[1], KEYS[2], ARGV[1]) then return 1 end
return 0
"""
)

# KEYS: the vehicle's live pointer, its track, its shard's index (one slot). ARGV: session-key prefix,
# cutoff. Returns the ended session's id when it was live, else ''.
END_VEHICLE_SESSION = (
    END_LIVE_SESSION_FN
    + """
return end_live_session(KEYS[1], KEYS[2], KEYS[3], ARGV[1], ARGV[2])
"""
)

# The fix stream (store.redis_fixlog.RedisFixLog). KEYS: the stream, its id counter (one slot: {fixes}).
# ARGV: the buffer, then for each entry session id, vehicle id, pipeline, n, times, lengths and data of its
# n fixes (store.redis_fix_entries). Gives the fixes the next n ids of the counter (dense: a consumer's
# resume can tell exactly how many events it missed), appends each entry with its last fix's id, and
# trims the entries whose fixes are all older than the buffer. Returns the last id given.
APPEND_FIXES_FN = """
local function append_fixes(stream, counter, buffer, first)
  local total = 0
  for b = first, #ARGV, 7 do total = total + tonumber(ARGV[b + 3]) end
  local last = redis.call('INCRBY', counter, total)
  local oldest = string.format('%d-0', math.max(last - tonumber(buffer) + 1, 0))
  local id = last - total
  for b = first, #ARGV, 7 do
    id = id + tonumber(ARGV[b + 3])
    redis.call('XADD', stream, 'MINID', oldest, string.format('%d-0', id), 's', ARGV[b], 'v', ARGV[b + 1],
      'p', ARGV[b + 2], 'n', ARGV[b + 3], 't', ARGV[b + 4], 'l', ARGV[b + 5], 'd', ARGV[b + 6])
  end
  return last
end
"""
PUBLISH_FIXES = APPEND_FIXES_FN + "return append_fixes(KEYS[1], KEYS[2], ARGV[1], 2)\n"

# A batch's compare-and-rename with its fix events appended to the fix stream in the same script, on a single
# server, where the session's keys and the stream's share the server (a cluster keeps them in different
# slots and appends apart). KEYS: as COMPARE_AND_RENAME's first four, the stream, its id counter and,
# optionally, the cached RSU map's token. ARGV: as COMPARE_AND_RENAME's first four, that map's token (or
# ''), the buffer, then the fixes as PUBLISH_FIXES takes them. The fixes are appended only if the record was
# applied, so a refused batch publishes nothing and the stream's order is the order of the applied batches.
COMPARE_AND_RENAME_PUBLISHING = (
    APPEND_FIXES_FN
    + "local token_key = KEYS[7]"
    + _COMPARE_AND_RENAME_BODY
    + "if #ARGV > 6 then append_fixes(KEYS[5], KEYS[6], ARGV[6], 7) end\nreturn 1\n"
)

# KEYS: the kind's document hash. ARGV: key, text. Writes only if the key is there; returns 1 if written.
REPLACE_DOCUMENT = """
if redis.call('HEXISTS', KEYS[1], ARGV[1]) == 1 then
  redis.call('HSET', KEYS[1], ARGV[1], ARGV[2])
  return 1
end
return 0
"""

# KEYS: the lease's key. ARGV: owner, ttl ms. Takes the lease when it is free (expired keys are gone) or
# renews it when it is the owner's; returns 1 when the owner holds it afterwards.
ACQUIRE_LEASE = """
local holder = redis.call('GET', KEYS[1])
if holder == false or holder == ARGV[1] then
  redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[2])
  return 1
end
return 0
"""

# KEYS: the base-station hash, the station's epoch window (sorted set scored by GPS s).
# ARGV: station id, how many epochs to keep, then (score, member) pairs.
# Returns the window's size after, or -1 (the station is not registered; nothing written).
ADD_BASE_EPOCHS = """
if redis.call('HEXISTS', KEYS[1], ARGV[1]) == 0 then
  return -1
end
for i = 3, #ARGV, 2 do
  redis.call('ZREMRANGEBYSCORE', KEYS[2], ARGV[i], ARGV[i])
  redis.call('ZADD', KEYS[2], ARGV[i], ARGV[i + 1])
end
local keep = tonumber(ARGV[2])
local size = redis.call('ZCARD', KEYS[2])
if size > keep then
  redis.call('ZREMRANGEBYRANK', KEYS[2], 0, size - keep - 1)
  size = keep
end
return size
"""

# KEYS: the base-station hash. ARGV: station id, value. Replaces the value only if the station exists.
# Returns 1 if replaced, 0 if the station is not registered (nothing written).
REPLACE_BASE_STATION = """
if redis.call('HEXISTS', KEYS[1], ARGV[1]) == 0 then
  return 0
end
redis.call('HSET', KEYS[1], ARGV[1], ARGV[2])
return 1
"""

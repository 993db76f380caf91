"""The location notifier: turns the vehicles' latest fixes into MEC 013 notifications and POSTs them.

Every worker runs one :class:`LocationNotifier` task, but only the holder of the store lease
``location-notifier`` works: each poll (EDGEPOS_LOCATION_POLL_S) a worker that sees subscriptions takes
or renews the lease, and only the holder compares the fixes with the zones, queues notifications in the
subscriptions' documents and sends them. Two workers sharing a store (SQLite, Redis) therefore never both
send the same notification while the holder is alive; if it dies, another worker takes the lease when it
runs out (LEASE_POLLS polls, at least LEASE_MIN_S) and goes on from the state in the documents.

The guarantee is at-least-once per crossing: a notification leaves the document only after its callback
answered 2xx and that removal was written; a holder that stalls past its lease between the two could
let the next holder send it again. Crossings are seen at poll resolution: a vehicle that enters and
leaves a zone between two polls is not notified.

Delivery: a subscription's notifications go out in order, one POST each (httpx, EDGEPOS_CALLBACK_TIMEOUT_S,
redirects not followed, so a callback cannot lead elsewhere than its allowed host). A poll starts no POST
after half the lease (which is at least twice the timeout), so the holder's last POST ends before its lease
runs out: the rest wait for the next poll. Any answer but 2xx, or
none, is a failure: the subscription waits EDGEPOS_CALLBACK_BACKOFF_S, doubled per further failure (at
most 300 s), and after EDGEPOS_CALLBACK_MAX_FAILURES consecutive failures it expires (is deleted).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import socket
import time
from collections.abc import Callable
from typing import Any

import httpx

from edgepos.api.location import subscriptions as subs
from edgepos.api.location.fixes import LatestFix, latest_fixes
from edgepos.api.location.zones import Zone, load_zones
from edgepos.api.settings import Settings
from edgepos.geo import GeodeticOrigin
from edgepos.store.base import SessionStore

logger = logging.getLogger("edgepos.api")

LEASE = "location-notifier"
LEASE_POLLS = 5
LEASE_MIN_S = 5.0


class LocationNotifier:
    """One worker's side of the notifier (see the module's docstring)."""

    def __init__(
        self,
        store: SessionStore,
        settings: Settings,
        origin: GeodeticOrigin | None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.store = store
        self.settings = settings
        self.origin = origin
        self.clock = clock
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{secrets.token_hex(4)}"
        self.lease_s = max(
            LEASE_MIN_S, LEASE_POLLS * settings.location_poll_s, 2.0 * settings.callback_timeout_s
        )

    async def run(self) -> None:
        """Poll until cancelled; a failing poll (store down) is logged and the next one tries again."""
        async with httpx.AsyncClient(
            timeout=self.settings.callback_timeout_s, follow_redirects=False
        ) as client:
            while True:
                await asyncio.sleep(self.settings.location_poll_s)
                try:
                    await self.poll(client)
                except Exception:  # keep polling: a transient store error must not end the task
                    logger.exception(
                        "location notifier poll failed", extra={"event": "location_notifier_failed"}
                    )

    async def poll(self, client: httpx.AsyncClient) -> bool:
        """One look at every subscription; False when there were none or another worker holds the lease."""
        documents = await self.store.list_documents(subs.KIND)
        if not documents:
            return False
        if not await self.store.acquire_lease(LEASE, self.owner, self.lease_s):
            return False
        loaded = {key: json.loads(text) for key, text in documents.items()}
        watched: set[str] | None = set()
        for document in loaded.values():
            vehicles = subs.watched_vehicles(document)
            if vehicles is None or watched is None:
                watched = None
            else:
                watched.update(vehicles)
        zones = await load_zones(self.store)
        fixes = await latest_fixes(self.store, watched)
        # deliveries stop well inside the lease, so that no other worker takes it while this one still sends
        until = time.monotonic() + self.lease_s / 2.0
        await asyncio.gather(
            *(self._serve(client, key, doc, zones, fixes, until) for key, doc in loaded.items())
        )
        return True

    async def _serve(
        self,
        client: httpx.AsyncClient,
        key: str,
        document: dict[str, Any],
        zones: dict[str, Zone],
        fixes: dict[str, LatestFix],
        until: float,
    ) -> None:
        now = self.clock()
        if document["expires_at"] is not None and now >= document["expires_at"]:
            await self.store.delete_document(subs.KIND, key)
            logger.info("location subscription ended", extra={"event": "subscription_expired", "id": key})
            return
        changed = subs.advance(document, zones, fixes, self.origin, now)
        if document["pending"] and now >= document["retry_at"]:
            changed = True
            await self._deliver(client, document, until)
            if document["failures"] >= self.settings.callback_max_failures:
                await self.store.delete_document(subs.KIND, key)
                logger.warning(
                    "location subscription expired after failed deliveries",
                    extra={"event": "subscription_failed", "id": key, "failures": document["failures"]},
                )
                return
        if changed:
            await self.store.replace_document(subs.KIND, key, subs.encode(document))

    async def _deliver(self, client: httpx.AsyncClient, document: dict[str, Any], until: float) -> None:
        """POST the pending notifications in order until one fails or the poll's time is up (``until``,
        monotonic); the rest wait for the next poll."""
        url = document["callback"]
        # the allowed hosts are checked again: the list may have changed since the subscription was made
        problem = subs.callback_problem(url, self.settings.callback_host_set)
        while document["pending"] and time.monotonic() < until:
            reason = problem
            if reason is None:
                try:
                    response = await client.post(url, json=document["pending"][0])
                    reason = None if 200 <= response.status_code < 300 else f"answered {response.status_code}"
                except httpx.HTTPError as error:
                    reason = f"{type(error).__name__}: {error}"
            if reason is not None:
                subs.record_failure(document, self.clock(), self.settings.callback_backoff_s)
                logger.warning(
                    "location notification not delivered",
                    extra={"event": "notification_failed", "id": document["id"], "reason": reason},
                )
                return
            document["pending"].pop(0)
            document["failures"] = 0
            document["retry_at"] = 0.0

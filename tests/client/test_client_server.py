"""The blocking client against a real server process over a real loopback socket."""

from __future__ import annotations

import pytest
from clienthelp import ADMIN_KEY, INITIAL_STATE, batch, scenario_rsus
from edgepos_client import Conflict, EdgeposClient, NotFound, Unauthorized

pytestmark = pytest.mark.slow


def test_session_driven_over_a_socket(server_url: str) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=10.0) as client:
        assert client.put_rsus(scenario_rsus()) == len(scenario_rsus())
        session = client.create_session("socket-car", initial_state=INITIAL_STATE)
        fixes = [fix for first in range(0, 60, 20) for fix in client.send_batch(session, batch(first, 20))]
        assert len(fixes) == 60 and session.last_seq == 3
        assert all(fix.status in ("initialised", "tracking") for fix in fixes)
        assert abs(fixes[-1].x - 10.0 * 3.0) < 5.0  # 3 s at 10 m/s east, from the origin
        replay = client.send_batch(
            session, batch(40, 20), seq=3
        )  # the last batch again: answered, not re-applied
        assert replay == fixes[40:]
        info = client.get_session(session)
        assert (info.last_seq, info.batches, info.epochs) == (3, 3, 60)
        with pytest.raises(Conflict):
            client.send_batch(session, batch(0, 20), seq=2)
        client.delete_session(session)
        with pytest.raises(NotFound):
            client.delete_session(session.session_id)  # with the admin key: gone
        with pytest.raises(Unauthorized):
            client.delete_session(session)  # with its own token: the token opens nothing any more

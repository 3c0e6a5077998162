"""The robot is another computer (issue 41): a server (``aesop up --role server``) here and
a robot (``aesop up --role robot``) in a network namespace of its own, joined by a veth pair
(real addresses, a real interface), their routers linked over mutual TLS through a fault
proxy of the tests' own (these kernels have no ``tc netem``). Each row of the fault table
is a flight judged on the vehicle's truth: it ends where the decision the loop acted on
sent it, with no tick outside the scene's limits; a silent link is a silent detector (an
anomaly, the fallback at K when it lasts), never a violation; the link comes back without
restarting anything; no write the server acknowledged across the link is lost.

Needs root for the namespace (``ip netns``), as ``make test`` runs on these machines."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tools.link.netns import missing
from tools.link.rig import FAULTS, Fault, Flight, Rig

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    why = missing()
    assert why is None, f"the two-host tests need a network namespace: {why}"
    with Rig(tmp_path_factory.mktemp("link"), name="aesoptest41") as rig:
        yield rig


def fly(rig: Rig, fault: Fault) -> Flight:
    """A delay alone flies scenario 2a (the decision must be the LLM's, the blue box); a
    stall, a cut or a restart comes into the nominal flight, where the silence is the
    anomaly."""
    flight = rig.fly(fault, "1" if fault.event else "2a")
    print(f"{fault.name}: the loop counted {flight.loop}; {flight.row}")
    return flight


@pytest.mark.parametrize("fault", FAULTS, ids=[f.name for f in FAULTS])
def test_a_flight_across_the_link_ends_safely_where_it_should(rig: Rig, fault: Fault) -> None:
    flight = fly(rig, fault)
    row = flight.row
    assert row["outcome"] == "ok", row
    assert row["constraint_violations"] == 0
    assert flight.lost == [], f"acknowledged, then lost: {flight.lost}"
    assert flight.acked, "no write crossed the link"
    assert flight.verdict_ms, "no verdict crossed the link"
    if not fault.event:  # a delay: the LLM's decision, through the link both ways
        assert row["decision"] == "alternative landing site" and row["ended_in"] == "blue-box"
        return
    # silence is an anomaly the loop raised (its own count: what it said on the bus during a
    # router's outage is lost with it), and the link came back without a restart
    assert flight.unmonitored_ticks > 0, (flight.loop, row)
    assert flight.reconnect_s is not None, "no verdict after the link came back"
    if fault.cut_s > 10:  # longer than K: committed to the fallback, in its region
        assert flight.fallback, row

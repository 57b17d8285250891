"""Deliveries: objects put back on their shelves during a shift.

A picked object is gone: a later task for it is skipped as "picked by ...",
and a shift longer than the stock runs out of work.  A delivery (a
``restock OBJECT`` line in a task list, or ``coapkb team --tasks N``,
which restocks an object before its list draws it again) brings it back,
returned or new, to the place the Location KB's files give it:

1. once its earlier pick in this feed is in the KB (or, with the world
   here, tried at the shelf): a delivery does not overtake the pick it undoes;
2. in the KB, when the robots write what they do: a SPARQL Update to a
   live holder of the Location module of the cluster fed, by PATCH with
   write concern ``all``, as ``coapkb update`` sends it.  It deletes the
   pick, the delivery and a missing report, and puts the object on its
   shelf; the holder spreads it to the others.  A late try of the pick's
   own write cannot take it off the shelf again: the holder made that
   write once, under its id (:mod:`coapkb.kb.write_ids`);
3. in the world's truth (:mod:`coapkb.world`), so that the robot sent
   finds it there: in this process, or over the world's socket;
4. the cluster's next task for the object says ``restocked``: every robot
   forgets the claim it remembers from the earlier decision, alike.

A read-only team's KB never recorded the pick: steps 3 and 4 alone.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from .. import clock
from ..errors import CoapkbError
from ..kb.client import KBClient, WriteShort
from ..kb.named_updates import NamedUpdate
from ..kb.results import expect_select
from ..kb.store import KnowledgeBase
from ..kb.write_concern import Ack
from ..security import client_security, load_identity
from ..security.errors import SecurityError
from ..transport import ClientSecurity
from ..transport.base import ClientTransport, Endpoint
from ..world import LOCATION_NS
from ..world.service import WorldClient
from ..world.truth import WorldTruth
from .tasks import FeederError

log = logging.getLogger(__name__)

#: How long a delivery waits for the pick it follows to be in the KB (or off
#: the shelf) while no robot finishes a job, and how often it looks.
PICK_WAIT_S = 30.0
POLL_S = 0.1

#: An object's place: aisle, rack, bin.
Place = tuple[int, int, int]
#: Whose key writes a delivery into the KB: an operator's (role ``client``),
#: as ``coapkb update`` writes; the feeder's role posts tasks only.
OPERATOR_IDENTITY = "operator"


def shelf_places(location_kb: KnowledgeBase) -> dict[str, Place]:
    """Every object's place as the Location KB's files give it, by its local name."""
    result = location_kb.query(
        f"PREFIX : <{LOCATION_NS}> SELECT ?o ?a ?r ?b WHERE "
        "{ ?o :Inventory_aisle_no ?a ; :Inventory_rack_no ?r ; :Inventory_bin_no ?b }",
        row_limit=10_000_000,
    )
    return {str(o).rsplit("#", 1)[-1]: (int(str(a)), int(str(r)), int(str(b)))
            for o, a, r, b in expect_select(result, "the shelves").rows}


def operator_security(transport: str, team_dir: Path | None, expected: Mapping[str, str]) -> ClientSecurity | None:
    """The client side a delivery is written with: the team's operator key
    (None for an insecure team); a :class:`FeederError` if there is none."""
    if team_dir is None:
        return None
    try:
        return client_security(transport, load_identity(team_dir, OPERATOR_IDENTITY), dict(expected))
    except SecurityError as exc:
        raise FeederError(f"a delivery is written with the team's {OPERATOR_IDENTITY} key: {exc}") from None


@dataclass
class Restocker:
    """Puts objects back: into the KB (``holders``: per cluster, the robots
    holding the Location module and where they serve; empty for a team that
    writes nothing) and into ``world``."""

    client: ClientTransport
    places: Mapping[str, Place]
    holders: Sequence[Sequence[tuple[str, Endpoint]]] = ()
    world: WorldTruth | WorldClient | None = None
    timeout_s: float = 10.0
    pick_wait_s: float = PICK_WAIT_S
    #: Deliveries made.
    done: int = 0

    async def restock(self, obj: str, cluster: int, picked: bool, down: Collection[str] = (),
                      jobs_done: Callable[[], int] | None = None) -> None:
        """Deliver ``obj`` back, in the KB of cluster ``cluster`` (0-based)
        and the world; ``picked``: this feed assigned it earlier, so its pick
        is waited for first, as long as the robots finish jobs (``jobs_done``:
        how many so far; the robots may decide far ahead of their wheels).
        Raises :class:`FeederError`."""
        place = self.places.get(obj)
        if place is None:
            raise FeederError(f"restock {obj}: the Location KB's files give it no place (aisle, rack, bin)")
        holders = [(r, e) for r, e in (self.holders[cluster] if self.holders else ()) if r not in down]
        if self.holders and not holders:
            raise FeederError(f"restock {obj}: no live robot of cluster {cluster + 1} holds the Location KB")
        kb = KBClient(self.client, timeout=self.timeout_s, cache=False)
        if picked:
            await self._after_pick(kb, obj, holders[0][1] if holders else None, jobs_done or (lambda: 0))
        if holders:
            await self._write(kb, obj, place, holders)
        if isinstance(self.world, WorldTruth):
            self.world.restock(obj)
        elif self.world is not None:
            try:
                await self.world.restock(obj)
            except CoapkbError as exc:
                raise FeederError(f"restock {obj}: {exc}") from None
        self.done += 1
        log.info("restocked %s at aisle %d, rack %d, bin %d", obj, *place)

    async def _after_pick(self, kb: KBClient, obj: str, holder: Endpoint | None, jobs_done: Callable[[], int]) -> None:
        """Wait until the earlier pick of ``obj`` is in ``holder``'s KB (or,
        with no KB to read, off the shelf of the world here), while jobs get done."""
        deadline = clock.monotonic() + self.pick_wait_s
        done = jobs_done()
        while clock.monotonic() < deadline or jobs_done() != done:
            if jobs_done() != done:
                done, deadline = jobs_done(), clock.monotonic() + self.pick_wait_s
            if holder is not None:
                try:
                    rows = expect_select(await kb.named(holder, "pick-place", {"name": obj}), "pick-place").as_dicts()
                except CoapkbError:
                    rows = []
                if any(r.get("picked_by") is not None or r.get("missing_task") is not None for r in rows):
                    return
            elif isinstance(self.world, WorldTruth):
                if obj in self.world.taken or obj in self.world.looked_for:
                    return
            else:
                return  # nothing to read it from: delivered at once
            await asyncio.sleep(POLL_S)  # polling the KB (or the world) for the pick
        log.warning("restock %s: its earlier pick did not show, and no job was done for %.0f s; delivered anyway",
                    obj, self.pick_wait_s)

    async def _write(self, kb: KBClient, obj: str, place: Place, holders: Sequence[tuple[str, Endpoint]]) -> None:
        update = [NamedUpdate("restock", (obj, *place))]
        write_id = kb.new_write_id()  # one delivery, one id, whichever holder takes it
        failure: CoapkbError | None = None
        for robot_id, endpoint in holders:
            try:
                await kb.write(endpoint, update, ack=Ack.ALL, write_id=write_id)
                return
            except WriteShort:
                return  # made, and it spreads from there: not sent to another holder
            except CoapkbError as exc:  # QueryFailed, TransportError
                failure = exc
                log.warning("restock %s: %s did not take it: %s", obj, robot_id, exc)
        raise FeederError(f"restock {obj}: no holder of the Location KB took it ({failure})")

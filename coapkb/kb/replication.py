"""Keeps every holder of a module in step: pushes each write, and walks
the holders for what anyone missed (anti-entropy).

It speaks only the transport interface (a request to ``/kb/sync`` on a
peer), so it runs over every transport and under its security.

* **Push.**  A local write's delta goes to every holder of the module this
  robot knows (its cluster's holders and its peers in other clusters) at
  once.  The write is answered once as many of them have it as the writer
  asked (its write concern, :mod:`.write_concern`): by default one, so an
  acknowledged write lives on two robots.  A holder in another cluster passes a
  delta new to it on to the holders it knows (its cluster, and the next
  cluster), so a write crosses the team cluster by cluster, each robot
  sending it at most once to each holder it knows.
* **Anti-entropy.**  Every ``sync_every_s`` (with jitter) the robot sends
  one holder its causal context, round robin (the next if that one does
  not answer, a standby if none does); the holder answers with the
  deltas the context lacks (from its journal) or, when its journal no
  longer has them, its whole written state, and with its own context.  The
  exchange goes both ways: what the holder lacks of this robot's is pushed
  right after.  What it costs grows with what was missed, not with the KB.
* **Compaction.**  A delta every peer's last known context holds leaves the
  journal.
* **Who may replicate.**  A sync carrying changes of a module is taken only
  from a robot known to hold that module (the security layer authenticated
  it: :attr:`Request.peer`), and only if every writer it names is an
  incarnation of such a robot; else 4.03 and nothing changes.  A question
  (a context alone) is a read, answered to any robot not known to lack the
  module.  A writer ``Robot1.<boot>`` is robot ``Robot1``'s incarnation.
  Without ``team`` (every holder of each module) a robot knows the holders
  its configuration names (its cluster's, its replicas); a writer of another
  cluster is then taken on the word of the holder that sends it.  An
  unprotected sender (``peer`` None) is not checked: there is nobody to
  check; writers known not to hold the module are still refused.
  (``docs/knowledge.md`` section 7, ``docs/security.md``.)
* **Lives.**  A robot kept in memory writes under one name across its
  lives once it has fenced the earlier ones out: every robot keeps the
  highest life it knows of each and refuses (4.03) a sync from a lower
  one (:mod:`.life_fence`).
* **Refused at the bound.**  A delta the replica does not take (its dots past
  a gap would pass ``cloud_max``) is answered 5.03 with Max-Age, never 2.04:
  the sender must not count it as held here; it comes again at catch-up.

The parts: :mod:`.sync_client` sends pushes and questions and takes the
answers in, :mod:`.sync_handler` answers ``/kb/sync``, :mod:`.anti_entropy`
runs the rounds, the catch-up and compaction; the :class:`Replicator`
here joins them and waits for a write's acknowledgements.  Messages:
:mod:`coapkb.wire.sync`.  Model: :mod:`.replica`.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Collection, Mapping, Sequence

from ..cancelling import cancel_and_wait
from ..transport.base import ClientTransport
from ..transport.messages import Request, Response
from ..transport.router import Router
from .anti_entropy import AntiEntropy
from .life_fence import LifeFence
from .live import LiveKB, Written
from .replication_settings import SYNC_PATH, Holder, ReplicationSettings, ReplicationStats
from .sync_access import SyncAccess, writer_robot
from .sync_client import SyncClient
from .sync_handler import SyncHandler
from .write_concern import DEFAULT_ACK, Ack, Reached

__all__ = ["SYNC_PATH", "Holder", "ReplicationSettings", "ReplicationStats", "Replicator", "writer_robot"]


class Replicator:
    """One robot's side of replication (see the module docstring): its
    parts are :attr:`outgoing`, :attr:`incoming` and :attr:`anti_entropy`."""

    def __init__(
        self,
        live: LiveKB,
        client: ClientTransport,
        holders: Sequence[Holder],
        *,
        settings: ReplicationSettings | None = None,
        rng: random.Random | None = None,
        team: Mapping[str, Collection[str]] | None = None,
    ) -> None:
        """``team``: every robot holding each module, across the team; a
        robot it does not list holds nothing.  None: the holders ``live``
        and ``holders`` name (see the module docstring)."""
        self.live = live
        self.client = client
        self.settings = settings or ReplicationSettings()
        self.holders: dict[str, list[Holder]] = {
            module: [h for h in holders if module in h.modules and not h.standby] for module in live.names
        }
        #: Per module, the holders asked only when the usual ones do not answer.
        self.standbys: dict[str, list[Holder]] = {
            module: [h for h in holders if module in h.modules and h.standby] for module in live.names
        }
        me = writer_robot(live.writer)
        #: Who may replicate which module (:mod:`.sync_access`).
        self.access = SyncAccess(
            me,
            {module: frozenset(team.get(module, ())) if team is not None
             else frozenset(live.holders.get(module, ())) | {h.name for h in holders if module in h.modules}
             for module in live.names},
            frozenset({me, *(h.name for h in holders), *(r for robots in live.holders.values() for r in robots)}),
            listed=team is not None,
        )
        self.stats = ReplicationStats()
        #: The lives of the robots kept in memory (:mod:`.life_fence`).
        self.fence = LifeFence()
        self.outgoing = SyncClient(live, client, self.access, self.settings, self.stats, self.fence)
        #: (module, holder) -> the last context it told us
        self.known = self.outgoing.known
        self.incoming = SyncHandler(live, self.holders, self.access, self.outgoing, self.settings, self.stats,
                                    lambda: self.anti_entropy.catching_up)
        # Seeded by the writer when not given: runs repeat, and robots' rounds still differ.
        self.anti_entropy = AntiEntropy(live, self.holders, self.outgoing, self.settings, self.stats,
                                        rng or random.Random(live.writer), self.standbys)

    # -------------------------------------------------------------- serving

    def mount(self, router: Router) -> None:
        self.incoming.mount(router)

    async def handle_sync(self, request: Request) -> Response:
        return await self.incoming.handle_sync(request)

    # -------------------------------------------------------------- writing

    async def replicate(self, written: Written) -> int:
        """Push a local write to the holders of its modules; how many other
        holders had it when it returned: at the first acknowledgement of
        every module, or at the ack timeout (:meth:`acknowledge` at ``2``)."""
        return (await self.acknowledge(written, Ack.TWO)).holders - 1

    async def acknowledge(self, written: Written, ack: Ack = DEFAULT_ACK) -> Reached:
        """Push a local write to every holder of the modules it changed, and
        wait until it reached ``ack`` (:mod:`.write_concern`), every push
        ended or the ack timeout passed; how far it reached then.

        ``local`` waits for nothing.  ``2`` is reached when one other holder
        of every module changed confirmed it (a module with no other holder
        needs none), ``all`` when every holder pushed to did.  The pushes
        not waited for go on."""
        wanted = {module: frozenset(h.name for h in self.holders[module]) for module in written.deltas}
        made = written.made
        pushes = {
            self.outgoing.spawn(self.outgoing.push(holder, module, [delta], made)): (module, holder.name)
            for module, delta in written.deltas.items()
            for holder in self.holders[module]
        }
        confirmed: dict[str, set[str]] = {module: set() for module in wanted}
        failed: set[str] = set()
        reached = _reached(wanted, confirmed, failed)
        pending = set(pushes)
        if ack == Ack.LOCAL:
            return reached
        try:
            async with asyncio.timeout(self.settings.ack_timeout_s):
                while pending and not reached.level.covers(ack):
                    done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                    for task in done:
                        module, name = pushes[task]
                        if not task.cancelled() and task.exception() is None and task.result():
                            confirmed[module].add(name)
                        else:
                            failed.add(name)
                    reached = _reached(wanted, confirmed, failed)
        except TimeoutError:
            pass
        return reached

    # -------------------------------------------------------- anti-entropy

    def start(self) -> None:
        self.anti_entropy.start()

    @property
    def catching_up(self) -> bool:
        """The catch-up at start has begun and not ended (:attr:`.AntiEntropy.catching_up`)."""
        return self.anti_entropy.catching_up

    async def caught_up(self) -> None:
        """Until the catch-up at start has asked every holder, at most
        :attr:`ReplicationSettings.read_after_catch_up_s` after it began."""
        await self.anti_entropy.caught_up()

    async def catch_up(self) -> None:
        """One exchange with every holder of every module (:meth:`.AntiEntropy.catch_up`)."""
        await self.anti_entropy.catch_up()

    async def sync_once(self) -> None:
        """One anti-entropy exchange per module, with its next holder that
        answers (:meth:`.AntiEntropy.sync_once`)."""
        await self.anti_entropy.sync_once()

    def compact(self) -> None:
        """Forget the deltas every holder had a round ago (:meth:`.AntiEntropy.compact`)."""
        self.anti_entropy.compact()

    async def aclose(self) -> None:
        await cancel_and_wait((self.anti_entropy.task, *self.outgoing.pushes))


def _reached(wanted: Mapping[str, frozenset[str]], confirmed: Mapping[str, set[str]],
             failed: Collection[str] = ()) -> Reached:
    """How far a write reached: ``wanted`` the other holders of each module
    it changed, ``confirmed`` those whose push was answered 2.04, ``failed``
    those a push to failed."""
    if not wanted:
        return Reached(Ack.ALL, changed=False)
    if all(confirmed[m] >= holders for m, holders in wanted.items()):
        level = Ack.ALL
    elif all(confirmed[m] or not holders for m, holders in wanted.items()):
        level = Ack.TWO
    else:
        level = Ack.LOCAL
    robots = frozenset().union(*wanted.values())
    # A robot holding several of the modules has the write once it confirmed each.
    holding = {r for r in robots if all(r in confirmed[m] for m, holders in wanted.items() if r in holders)}
    lacking = robots - holding
    return Reached(level, 1 + len(holding), 1 + len(robots), tuple(sorted(lacking - set(failed))),
                   tuple(sorted(lacking & set(failed))))

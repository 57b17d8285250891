"""Which faults a simulated run may meet, and the schedule a seed draws.

``--faults`` names the kinds (``kill,freeze,partition,loss=0.2,starve``);
:func:`draw_schedule` turns them and a seed into a :class:`Schedule`: link
behaviour for the whole run, and timed events on processes and links.  A
schedule stays inside the fault model the team claims to tolerate: at any
moment at most one robot of a cluster is dead, frozen or cut off (two of
three would leave no majority to grant leases, and the cluster could only
wait), and every freeze and partition heals.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

from ..errors import CoapkbError
from .network import LinkModel

#: Fault kinds that act on processes or links at a time.
EVENT_KINDS = ("kill", "freeze", "partition", "starve", "forge", "crash", "rejoin", "bounce")
#: Kinds that shape every link for the whole run, with their default amount.
LINK_KINDS = {"loss": 0.05, "burst": 0.02, "dup": 0.02, "jitter": 0.02, "late": 0.02, "hedge": 0.3}
#: The link kinds swarm testing draws for every seed, in their order...
_SWARM_KINDS = ("loss", "burst", "dup", "jitter")
#: ...and those it draws only where they are asked for, after them: a seed
#: without them draws its mix as it did before they existed.
_ASKED_KINDS = ("late", "hedge")
#: Everything at once, with default amounts (a forger, a power cut and a
#: rejoin cut off are asked for by name).
MIXED = "kill,freeze,partition,starve,loss,burst,dup,jitter"
#: Swarm testing: each seed draws which of the mix's kinds are on, how
#: often, for how long, and its links' amounts (up to three times the default).
SWARM = "swarm"
#: What a fault event may do (:meth:`coapkb.sim.run.SimulatedTeam.inject`).
ACTIONS = ("kill", "restart", "freeze", "resume", "cut", "heal", "starve", "freeze-picking", "cut-picking",
           "crash", "forge")
#: The most fault events a swarm schedule draws.
SWARM_EVENTS = 10


class FaultSpecError(CoapkbError, ValueError):
    """A ``--faults`` list that cannot be read."""


@dataclass(frozen=True)
class FaultMix:
    """The fault kinds a run may draw, and the link faults' amounts."""

    events: tuple[str, ...] = ()
    loss: float = 0.0
    burst: float = 0.0
    dup: float = 0.0
    jitter: float = 0.0
    #: Messages held back 0.5-3 s (:attr:`~coapkb.sim.network.LinkModel.late`).
    late: float = 0.0
    #: Retries sent as two exchanges (:attr:`~coapkb.sim.network.LinkModel.hedge`).
    hedge: float = 0.0
    #: Each seed draws its own mix from these kinds (:data:`SWARM`).
    swarm: bool = False

    @classmethod
    def parse(cls, text: str) -> FaultMix:
        """``kill,freeze,partition,loss=0.2,starve`` (``mixed``: every kind;
        ``none`` or empty: a fault-free run).  Amounts are probabilities
        (``loss=0.2`` or ``loss=20%``); ``jitter`` is in seconds."""
        events: list[str] = []
        amounts: dict[str, float] = {}
        swarm = False
        items = [i.strip() for i in text.replace("mixed", MIXED).split(",") if i.strip() and i.strip() != "none"]
        for item in items:
            name, sep, value = item.partition("=")
            if name == SWARM and not sep:
                swarm = True
            elif name in EVENT_KINDS and not sep:
                if name not in events:
                    events.append(name)
            elif name in LINK_KINDS:
                amounts[name] = _amount(name, value) if sep else LINK_KINDS[name]
            else:
                known = ", ".join([*EVENT_KINDS, *(f"{k}[=P]" for k in LINK_KINDS), "mixed", SWARM])
                raise FaultSpecError(f"unknown fault {item!r} (choose from {known})")
        return cls(tuple(events), **amounts, swarm=swarm)

    @property
    def lossy(self) -> bool:
        return self.loss > 0 or self.burst > 0

    def link(self) -> LinkModel:
        """Every link's behaviour: a radio's (30 ms one way) once anything is lost, else a LAN's."""
        if self.lossy:
            return LinkModel(delay_s=0.03, jitter_s=max(self.jitter, 0.005), loss=self.loss,
                             burst=self.burst, duplicate=self.dup, late=self.late, hedge=self.hedge)
        return LinkModel(delay_s=0.001, jitter_s=max(self.jitter, 0.0005), duplicate=self.dup, late=self.late,
                         hedge=self.hedge)

    def describe(self) -> str:
        parts = list(self.events)
        parts += [f"{k}={getattr(self, k):g}" for k in LINK_KINDS if getattr(self, k)]
        parts += [SWARM] if self.swarm else []
        return ",".join(parts) or "none"

    def drawn(self, rng: random.Random) -> FaultMix:
        """One seed's mix in swarm testing: each kind on or off, each link
        amount between none and three times the given one (a lossy mix stays
        lossy: the robots are configured for it)."""
        if not self.swarm:
            return self
        kinds = tuple(k for k in self.events if rng.random() < 0.6) or (rng.choice(self.events),) if self.events else ()
        amounts = {k: round(rng.uniform(0, 3 * getattr(self, k)), 4) if rng.random() < 0.7 else 0.0
                   for k in _SWARM_KINDS}
        if self.lossy and not (amounts["loss"] or amounts["burst"]):
            amounts["loss"] = round(rng.uniform(0, 3 * max(self.loss, self.burst)), 4)
        amounts["burst"] = min(amounts["burst"], 0.5)
        for kind in _ASKED_KINDS:  # probabilities: at most 1
            asked = getattr(self, kind)
            amounts[kind] = round(min(1.0, rng.uniform(0, 3 * asked)), 4) if asked and rng.random() < 0.7 else 0.0
        return FaultMix(kinds, loss=amounts["loss"], burst=amounts["burst"], dup=amounts["dup"],
                        jitter=amounts["jitter"], late=amounts["late"], hedge=amounts["hedge"])


def _amount(name: str, value: str) -> float:
    try:
        amount = float(value[:-1]) / 100 if value.endswith("%") else float(value)
    except ValueError:
        raise FaultSpecError(f"{name}= expects a number, got {value!r}") from None
    top = 10 if name == "jitter" else 0.99 if name == "burst" else 1
    if name != "jitter" and amount > top and not value.endswith("%"):
        # coapkb bench's --loss is in percent: say how to write a percentage here.
        raise FaultSpecError(f"{name}={value}: P is a probability from 0 to {top:g} "
                             f"(write {name}={amount / 100:g} or {name}={value}% for {value} %)")
    if not 0 <= amount <= top:
        raise FaultSpecError(f"{name}={value} is out of range")
    return amount


@dataclass(frozen=True)
class FaultEvent:
    """One scheduled fault: ``action`` on ``targets`` at ``at_s`` (simulated seconds)."""

    at_s: float
    #: One of :data:`ACTIONS`.  freeze-picking and cut-picking: from ``at_s``
    #: until ``until_s``, the moment the robot starts a pick, freeze it (or cut
    #: it off from everyone) for ``amount`` s; crash: a power cut of every
    #: holder of a module of ``targets``; forge: a sync of the module of
    #: ``targets`` in its own writer name, sent to it with ``other``'s credential.
    action: str
    targets: tuple[str, ...]
    #: starve: the mean lateness of each loop turn, seconds; freeze-picking,
    #: cut-picking: how long the robot stays frozen or cut off; cut: the other side.
    amount: float = 0.0
    other: tuple[str, ...] = ()
    until_s: float = 0.0

    def __str__(self) -> str:
        who = "+".join(self.targets)
        if self.action == "cut":
            return f"cut {who}|{'+'.join(self.other)}@{self.at_s:.2f}s"
        if self.action == "starve":
            return f"starve {who}@{self.at_s:.2f}-{self.until_s:.2f}s({self.amount * 1000:.0f}ms)"
        if self.action == "crash":
            return f"crash holders of {who}@{self.at_s:.2f}s({self.amount:.2f}s)"
        if self.action == "forge":
            return f"forge {who} as {'+'.join(self.other)}@{self.at_s:.2f}s"
        if self.action.endswith("-picking"):
            return f"{self.action} {who}@{self.at_s:.2f}-{self.until_s:.2f}s({self.amount:.2f}s)"
        return f"{self.action} {who}@{self.at_s:.2f}s"


@dataclass(frozen=True)
class Schedule:
    link: LinkModel
    events: tuple[FaultEvent, ...] = field(default_factory=tuple)

    def __str__(self) -> str:
        model = self.link
        links = []
        if model.loss:
            links.append(f"loss {model.loss:.0%}")
        if model.burst:
            links.append(f"bursts {model.burst:.0%}")
        if model.duplicate:
            links.append(f"dup {model.duplicate:.0%}")
        if model.late:
            links.append(f"late {model.late:.0%}")
        if model.hedge:
            links.append(f"hedged retries {model.hedge:.0%}")
        return "; ".join([*(str(e) for e in self.events), *links]) or "no faults"


class _DraftSchedule:
    """A schedule being drawn: its events so far and who is out until when.

    Every draw from ``rng`` is made in one fixed order, event after event:
    a seed's schedule is part of what a run replays."""

    def __init__(self, clusters: list[list[str]], horizon_s: float, swarm: bool, rng: random.Random) -> None:
        self.clusters = clusters
        self.horizon_s = horizon_s
        self.swarm = swarm
        self.rng = rng
        self.events: list[FaultEvent] = []
        #: Robot -> until when it is out (dead, frozen or cut off): None = for good.
        self.out: dict[str, float | None] = {}
        self.cluster_of = {r: i for i, c in enumerate(clusters) for r in c}
        self.robots = [r for c in clusters for r in c]

    def free(self, robot: str, at: float) -> bool:
        """No robot of ``robot``'s cluster is out at ``at``."""
        cluster = self.cluster_of[robot]
        return all(until is not None and until < at for r, until in self.out.items() if self.cluster_of[r] == cluster)

    def draw(self, kind: str) -> None:
        """One event of ``kind`` (or none, when every robot it could hit is
        needed by its cluster): when, for how long, and on whom."""
        rng, horizon_s, robots = self.rng, self.horizon_s, self.robots
        at = round(rng.uniform(0.05, horizon_s), 3)
        longest = max(1.0, horizon_s * (3 if self.swarm and rng.random() < 0.5 else 0.5))
        lasting = round(rng.uniform(0.5, longest), 3)
        if kind == "starve":
            target = rng.choice(["feeder", *robots])
            self.events.append(FaultEvent(at, "starve", (target,), amount=round(rng.uniform(0.1, 1.5), 3),
                                          until_s=round(at + lasting, 3)))
            return
        if kind == "forge":
            # A teammate's credential used against a robot: a sync in the
            # robot's own writer name (its next dot), from one that may not hold the module.
            cluster = self.clusters[rng.randrange(len(self.clusters))]
            victim, forger = rng.sample(cluster, 2)
            self.events.append(FaultEvent(at, "forge", (victim,), other=(forger,)))
            return
        candidates = [r for r in robots if self.free(r, at) and self.free(r, at + lasting)]
        if kind == "partition" and rng.random() < 0.2:
            # The feeder cut off from everyone for a while.
            self.events.append(FaultEvent(at, "cut", ("feeder",), other=tuple(robots)))
            self.events.append(FaultEvent(round(at + lasting, 3), "heal", ("feeder",)))
            return
        if candidates:
            self.take_out(kind, rng.choice(candidates), at, lasting, longest)

    def take_out(self, kind: str, victim: str, at: float, lasting: float, longest: float) -> None:
        """``victim`` killed, frozen or cut off at ``at``, or caught by a trap
        there, for ``lasting`` s; or, for a crash, its whole cluster."""
        rng = self.rng
        if kind == "crash":
            # A power cut: every holder of one of the victim's modules at
            # once, all restarted later (outside the one-out-per-cluster
            # model, so the whole cluster counts as out meanwhile).
            for robot in self.clusters[self.cluster_of[victim]]:
                self.out[robot] = at + lasting
            self.events.append(FaultEvent(at, "crash", (victim,), amount=lasting))
            return
        if self.swarm and kind in ("freeze", "partition") and rng.random() < 0.4:
            # A trap: armed for ``lasting``, it springs at the robot's next pick.
            held = round(rng.uniform(0.5, longest), 3)
            self.out[victim] = at + lasting + held
            action = "freeze-picking" if kind == "freeze" else "cut-picking"
            self.events.append(FaultEvent(at, action, (victim,), amount=held, until_s=round(at + lasting, 3)))
            return
        if kind == "rejoin":
            # Killed, started again soon (while tasks are still posted, so
            # it joins at the next), and cut off from its cluster (not from
            # the feeder, whose post names it to join) the moment it is
            # back: it must take its teammates' membership once it hears
            # them, or, left out meanwhile, be fenced as any robot left out.
            back, held = round(at + min(lasting, 2.0), 3), round(rng.uniform(0.5, longest), 3)
            self.out[victim] = back + held
            mates = tuple(r for r in self.clusters[self.cluster_of[victim]] if r != victim)
            self.events += [FaultEvent(at, "kill", (victim,)), FaultEvent(back, "restart", (victim,)),
                            FaultEvent(back, "cut", (victim,), other=mates),
                            FaultEvent(round(back + held, 3), "heal", (victim,))]
            return
        if kind == "bounce":
            # Killed and started again at once, as a supervisor restarts a
            # crashed process: what its last life sent may still be on its
            # way (held back, or retried by nobody) when the next one starts.
            back = round(at + rng.uniform(0.05, 0.5), 3)
            self.out[victim] = back
            self.events += [FaultEvent(at, "kill", (victim,)), FaultEvent(back, "restart", (victim,))]
            return
        if kind == "kill":
            restart = rng.random() < 0.5
            self.out[victim] = at + lasting if restart else None
            self.events.append(FaultEvent(at, "kill", (victim,)))
            if restart:
                self.events.append(FaultEvent(round(at + lasting, 3), "restart", (victim,)))
        elif kind == "freeze":
            self.out[victim] = at + lasting
            self.events.append(FaultEvent(at, "freeze", (victim,)))
            self.events.append(FaultEvent(round(at + lasting, 3), "resume", (victim,)))
        else:
            self.out[victim] = at + lasting
            cluster = self.clusters[self.cluster_of[victim]]
            if rng.random() < 0.5:
                # One robot cut off from its cluster and the feeder.
                others = tuple(r for r in ["feeder", *self.robots] if r != victim)
            else:
                # A cluster split: the robot alone on one side, its teammates with the feeder on the other.
                others = tuple(r for r in cluster if r != victim)
            self.events.append(FaultEvent(at, "cut", (victim,), other=others))
            self.events.append(FaultEvent(round(at + lasting, 3), "heal", (victim,)))


def draw_schedule(mix: FaultMix, clusters: list[list[str]], horizon_s: float, rng: random.Random) -> Schedule:
    """The faults of one run: up to three events drawn from ``mix``'s kinds
    over the first ``horizon_s`` simulated seconds, at most one robot of a
    cluster out at a time.  In swarm testing the seed first draws its own
    mix (:meth:`FaultMix.drawn`), up to :data:`SWARM_EVENTS` events, outages
    up to three times as long as the run (long enough for the others to send
    a robot's tasks round again), and traps that freeze or cut off a robot
    at the moment it starts a pick."""
    swarm = mix.swarm
    mix = mix.drawn(rng)
    draft = _DraftSchedule(clusters, horizon_s, swarm, rng)
    for _ in range(rng.randint(1, SWARM_EVENTS if swarm else 3) if mix.events else 0):
        draft.draw(rng.choice(mix.events))
    events = sorted(draft.events, key=lambda e: e.at_s)
    return Schedule(mix.link(), tuple(events))

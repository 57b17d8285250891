"""The benchmark row: one run's result, and the results CSV it is a line of.

:class:`BenchRow`'s fields are the CSV columns, in order; their types say how
a CSV cell (text) or a ``coapkb bench --json`` value is read back, and the
fields marked with :func:`key` make a run's resume key.  Nothing else spells
the schema out.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..feeder.record import FateCounts

_KEY = "key"


def key_field(default: Any = dataclasses.MISSING) -> Any:
    """A field that is part of a run's identity (the resume key)."""
    if default is dataclasses.MISSING:
        return dataclasses.field(metadata={_KEY: True})
    return dataclasses.field(default=default, metadata={_KEY: True})


@dataclass(frozen=True, slots=True)
class BenchRow:
    """One benchmark run (see ``coapkb.bench.run`` for what each measure means).

    ``None`` is an empty cell: a measure the run did not get (it failed, or
    the column does not apply to its transport)."""

    # The run's key (which system, team, link, repetition and retransmission), then its measures.
    system: str = key_field()
    robots: int = key_field()
    tasks: int = key_field()
    bandwidth_kbps: float = key_field()
    loss_pct: float = key_field()
    rep: int = key_field()
    #: ``robust`` for CoAP (older results: the retired CON profiles), ``tcp`` for ZeroMQ (see ``retransmission_label``).
    retransmission_profile: str = key_field()
    ok: bool = False
    coordination_s: float | None = None
    completion_s: float | None = None
    wire_bytes: int | None = None
    wire_packets: int | None = None
    retransmissions: int | None = None
    query_p50_ms: float | None = None
    query_p99_ms: float | None = None
    # The system and how it ran.
    mode: str = ""
    transport: str = ""
    query_wire: str = ""
    seed: int | None = None
    emulation: str = ""
    app_bytes: int | None = None
    feeder_wire_bytes: int | None = None
    dropped_packets: int | None = None
    queue_drops: int | None = None
    remote_queries: int | None = None
    local_queries: int | None = None
    failed_queries: int | None = None
    spurious_retransmissions: int | None = None
    tasks_agreed: int | None = None
    tcp_aborts: int | None = None
    query_timeout_s: float | None = None
    task_timeout_s: float | None = None
    wall_s: float | None = None
    started_at: str = ""
    error: str = ""
    # The link columns added with the delay line.  Their defaults are what a
    # CSV written before them means: no delay, independent loss.
    delay_ms: float = key_field(0.0)
    jitter_ms: float = key_field(0.0)
    loss_model: str = key_field("random")
    #: Mean loss burst; 0 for independent loss, so it does not split the key.
    burst_len: float = key_field(0.0)
    # The fault-injection columns (``coapkb bench --fail``).  Their defaults
    # are what a CSV written before them means: one holder per KB module, no
    # failure injected.
    #: Robots of a cluster holding each KB module.
    replication: int = key_field(1)
    #: Robots killed and when, e.g. ``Robot2@6`` (several joined by ``+``).
    faults: str = key_field("")
    #: Seconds from a kill until the feeder declared the robot down (the longest, if several).
    fault_detected_s: float | None = None
    #: Tasks that went round again because their robot died before executing them.
    tasks_reassigned: int | None = None
    #: Tasks the team could not do: a KB module they need had no live holder.
    tasks_unavailable: int | None = None
    #: What protected the messages (the transport registry's mechanism name):
    #: ``oscore``, ``curve``, ``tls``, or ``none`` -- a CSV written before the column
    #: holds unprotected runs only.
    security: str = key_field("none")
    # Every task's fate (coapkb.feeder.record.FateCounts; tasks_reassigned and
    # tasks_unavailable above are two of them).  Empty in a CSV written before them.
    tasks_assigned: int | None = None
    tasks_skipped: int | None = None
    tasks_unassigned: int | None = None
    tasks_errors: int | None = None
    tasks_disagreements: int | None = None
    #: The robots' commonest reason for the unassigned tasks.
    unassigned_reason: str = ""
    #: On how many of the unassigned tasks that reason was the commonest.
    unassigned_reason_tasks: int | None = None
    #: The central server's share of ``wire_bytes`` (central systems; its link's
    #: load), and the busiest robot's share (what one robot's radio carried).
    central_wire_bytes: int | None = None
    robot_wire_bytes_max: int | None = None
    #: The robots' KBs took writes: every pick written (``coapkb bench --writable``).
    kb_writable: bool = key_field(False)
    #: Tasks whose robot did not find the object at the shelf.  Empty in a CSV written before it.
    tasks_not_found: int | None = None
    #: Facts a KB holder pushed to a robot before it asked (``remote_queries``
    #: are those asked).  Empty in a CSV written before pushes.
    pushed_answers: int | None = None

    def fates(self) -> FateCounts | None:
        """The tasks' fates, as ``coapkb team`` counts them; None for a row without them (an older CSV)."""
        from ..feeder.record import FateCounts  # the feeder package is heavy; report code reads rows without it

        columns = (self.tasks_assigned, self.tasks_skipped, self.tasks_unassigned, self.tasks_unavailable,
                   self.tasks_reassigned, self.tasks_errors, self.tasks_disagreements)
        counts = [n for n in columns if n is not None]
        if len(counts) < len(columns):
            return None
        assigned, skipped, unassigned, unavailable, reassigned, errors, disagreements = counts
        reason = self.unassigned_reason or None
        not_found = self.tasks_not_found or 0
        return FateCounts(
            tasks=sum(counts) + not_found, assigned=assigned, skipped=skipped,
            unassigned=unassigned, unavailable=unavailable, reassigned=reassigned,
            not_found=not_found, errors=errors,
            disagreements=disagreements, unassigned_reason=reason,
            unassigned_reason_tasks=self.unassigned_reason_tasks or 0,
        )

    def key(self) -> tuple[str, ...]:
        """The run's identity: rows with equal keys are the same run (a re-run
        replaces it).  Normalised to text so ``35`` and ``35.0`` are equal."""
        return tuple(_norm(getattr(self, name)) for name in KEY_COLUMNS)

    def to_dict(self) -> dict[str, Any]:
        """Column -> value, in column order (the ``--json`` line)."""
        return {name: getattr(self, name) for name in COLUMNS}

    def to_csv(self) -> dict[str, Any]:
        """Column -> cell for :class:`csv.DictWriter` (``None`` as an empty cell)."""
        return {name: "" if value is None else value for name, value in self.to_dict().items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BenchRow:
        """A row from CSV cells (text) or a ``--json`` line (typed values):
        each value parsed by its field's type; an empty or missing cell is the
        field's default; unknown columns are ignored."""
        kinds = _kinds()
        values = {}
        for name, kind in kinds.items():
            raw = data.get(name)
            if raw is None or raw == "":
                continue
            values[name] = _parse(kind, raw)
        return cls(**values)


def _norm(value: Any) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    text = str(value)
    with contextlib.suppress(ValueError):
        number = float(text)
        if number.is_integer() and "." in text:
            return str(int(number))
    return text


@cache
def _kinds() -> dict[str, type]:
    """Each field's value type, ``X | None`` reduced to ``X``."""
    hints = typing.get_type_hints(BenchRow)
    kinds = {}
    for f in dataclasses.fields(BenchRow):
        args = [a for a in typing.get_args(hints[f.name]) if a is not type(None)]
        kinds[f.name] = args[0] if args else hints[f.name]
    return kinds


def _parse(kind: type, raw: Any) -> Any:
    if kind is bool:
        return raw if isinstance(raw, bool) else str(raw).strip().lower() in ("true", "1", "yes")
    if kind is int:
        return int(float(raw))  # "12.0" from a spreadsheet round trip is still 12
    return kind(raw)


#: The CSV schema, in column order.
COLUMNS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(BenchRow))
#: The columns a row cannot do without (the rest have defaults: older CSVs lack them).
REQUIRED_COLUMNS: tuple[str, ...] = tuple(
    f.name for f in dataclasses.fields(BenchRow)
    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING)
#: A run's identity (see :meth:`BenchRow.key`).
KEY_COLUMNS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(BenchRow) if f.metadata.get(_KEY))


def read_rows(path: str | Path, *, latest_only: bool = True) -> list[BenchRow]:
    """The rows of a results CSV ([] if it does not exist).  With
    ``latest_only``, a key that was re-run (``--retry-failed``) keeps its last row."""
    path = Path(path)
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in REQUIRED_COLUMNS if c not in (reader.fieldnames or ())]
        if missing:
            raise ValueError(f"{path} is not a benchmark CSV: it has no column {', '.join(missing)}")
        rows = [BenchRow.from_dict(r) for r in reader]
    if not latest_only:
        return rows
    return list({r.key(): r for r in rows}.values())


def done_keys(path: str | Path, *, include_failed: bool = True) -> set[tuple[str, ...]]:
    """Keys of the runs already in the CSV (failed ones only if ``include_failed``)."""
    return {r.key() for r in read_rows(path) if include_failed or r.ok}


def append_rows(path: str | Path, rows: Iterable[BenchRow]) -> None:
    """Append rows; write the header first if the file is new or empty.  An
    existing file keeps its own header (columns it lacks are dropped)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header: list[str] = list(COLUMNS)
    new = not path.exists() or path.stat().st_size == 0
    if not new:
        with path.open(newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), list(COLUMNS))
    with path.open("a", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=header, extrasaction="ignore", restval="")
        if new:
            writer.writeheader()
        for row in rows:
            writer.writerow(row.to_csv())


def format_row(row: BenchRow) -> str:
    """One line of key numbers for a terminal."""
    head = (f"{row.system:<17} {row.robots}r {row.tasks:>2}t {row.bandwidth_kbps:g}k "
            f"{row.loss_pct:g}% rep{row.rep} {row.security}")
    if not row.ok:
        return f"{head}: FAILED after {row.wall_s or 0:.0f} s: {row.error or 'unknown'}"

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.0f}"

    line = (f"{head}: completion {row.completion_s or 0:.1f} s, wire {row.wire_bytes or 0:,} B "
            f"in {row.wire_packets or 0:,} pkts, retx {row.retransmissions}, "
            f"query p50/p99 {ms(row.query_p50_ms)}/{ms(row.query_p99_ms)} ms")
    fates = row.fates()
    if fates is not None:
        line += f"; {fates.line()}"
    if row.faults:
        line += (f"; killed {row.faults}: detected after {row.fault_detected_s} s, "
                 f"{row.tasks_reassigned} re-assigned, {row.tasks_unavailable} unavailable")
    return line

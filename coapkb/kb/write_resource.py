"""``PATCH`` and ``iPATCH`` of ``/kb`` on a writable knowledge base (RFC
8132): SPARQL Update text, a compact patch or named updates, made once
under their id however often they are sent (:mod:`.write_ids`), and
answered once they reached the write concern asked (:mod:`.write_concern`).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable
from typing import TYPE_CHECKING

from ..transport.messages import ContentFormat, Method, Request, Response, Status
from ..wire import codec
from .errors import KBError, QuerySyntaxError
from .live import LiveKB, NotHeld, PreconditionFailed, WriteTooLarge, Written
from .named_updates import decode_named_updates, is_named_updates, named_updates_sparql
from .replica import ReplicaFull
from .update import UpdateUnsupported, decode_patch, parse_update
from .write_concern import DEFAULT_ACK, Ack, Reached, ack_of_query, changed_line, encode_changed, short_line
from .write_ids import WID_PARAM, Remembered, WriteId, WriteTag, body_digest, parse_wid

if TYPE_CHECKING:
    from .limits import QueryLimits
    from .replication import Replicator


class WriteResource:
    """The write path of one writable KB: ``replicator`` (None: it is the
    only holder) spreads each write and says how far it reached."""

    def __init__(self, live: LiveKB, limits: QueryLimits, replicator: Replicator | None = None) -> None:
        self.live = live
        self.limits = limits
        self.replicator = replicator
        #: Writes made under an id and not answered yet (waiting for their
        #: write concern): a repeat waits for the same answer.
        self._answering: dict[WriteId, tuple[bytes, asyncio.Future[Response]]] = {}

    async def write(self, request: Request) -> Response:
        """PATCH/iPATCH ``/kb``: SPARQL Update text (0), or a compact patch or
        named updates (60, :mod:`.named_updates`); with ``?wid=``, made once
        however often it is sent (:mod:`.write_ids`)."""
        live = self.live
        try:
            ack = ack_of_query(request.query, {WID_PARAM: "WRITER.N"})
            wid = request.query.get(WID_PARAM)
            tag = None if wid is None else WriteTag(
                parse_wid(wid, request.peer), body_digest(request.method, request.content_format, request.payload))
        except ValueError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        # A holder that starts (again) takes writes once caught up, as it
        # answers reads: a delete or a WHERE acts on what it holds, and a
        # DELETE DATA sent to one whose catch-up was still on its way
        # removed nothing there while the value stayed on the others
        # (found in the simulator, seed 261 with messages held back).
        await caught_up(self.replicator)
        if tag is not None:
            repeat = await self._repeat(tag, ack, request.accept)
            if repeat is not None:
                return repeat
        size = len(request.payload)
        if size > self.limits.max_update_bytes:
            return Response.error(
                Status.REQUEST_ENTITY_TOO_LARGE,
                f"the update is {size} bytes; this robot takes at most {self.limits.max_update_bytes}",
            )
        try:
            if request.content_format in (None, ContentFormat.TEXT):
                try:
                    text = request.payload.decode("utf-8")
                except UnicodeDecodeError as exc:
                    return Response.error(Status.BAD_REQUEST, f"the update is not UTF-8: {exc}")
                if not text.strip():
                    return Response.error(Status.BAD_REQUEST, "empty update")
                if request.method == Method.IPATCH and _not_idempotent(text):
                    return Response.error(
                        Status.BAD_REQUEST, "DELETE/INSERT ... WHERE is not idempotent: send it with PATCH, not iPATCH"
                    )
                if self._catching_up() and _removes(text):
                    return self._held_back()
                written = live.update(text, if_match=request.if_match, tag=tag)
            elif request.content_format == ContentFormat.CBOR:
                body = codec.load_cbor(request.payload)
                if is_named_updates(body):
                    text = named_updates_sparql(decode_named_updates(body))
                    if self._catching_up() and _removes(text):
                        return self._held_back()
                    written = live.update(text, if_match=request.if_match, tag=tag)
                else:
                    deletes, inserts = decode_patch(request.payload)
                    if self._catching_up() and deletes:
                        return self._held_back()
                    written = live.patch(deletes, inserts, if_match=request.if_match, tag=tag)
            else:
                return Response.error(
                    Status.UNSUPPORTED_CONTENT_FORMAT,
                    "a write is SPARQL Update text (content-format 0), or a compact patch or named updates (60)",
                )
        except QuerySyntaxError as exc:
            return Response.error(Status.BAD_REQUEST, f"malformed SPARQL Update: {exc}")
        except codec.CodecError as exc:
            return Response.error(Status.BAD_REQUEST, f"malformed patch or named updates: {exc}")
        except (UpdateUnsupported, NotHeld) as exc:
            return Response.error(Status.UNPROCESSABLE_ENTITY, str(exc))
        except PreconditionFailed as exc:
            return Response.error(Status.PRECONDITION_FAILED, str(exc))
        except WriteTooLarge as exc:
            return Response.error(Status.REQUEST_ENTITY_TOO_LARGE, str(exc))
        except ReplicaFull as exc:
            return Response.error(Status.SERVICE_UNAVAILABLE, f"not written: {exc}", max_age=self.limits.retry_after_s)
        except KBError as exc:
            return Response.error(Status.BAD_REQUEST, str(exc))
        if tag is None:
            return await self._acknowledge(written, ack, request.accept)
        return await self._answer_once(tag, self._acknowledge(written, ack, request.accept))

    def _catching_up(self) -> bool:
        """This robot, started again, has still not heard its co-holders
        past the wait for them (asked before an update is parsed for what
        it removes: most writes come when it is not)."""
        return self.replicator is not None and self.replicator.catching_up

    def _held_back(self) -> Response:
        """5.03 for a write that removes or matches while :meth:`_catching_up`:
        it would act without what the co-holders hold.  A DELETE DATA tried
        again and sent to a holder restarted without its data folder, whose
        catch-up outlasted the wait (a co-holder starved, the link lossy),
        removed nothing there and was answered 2.04, while the value stayed
        on the others (simulator, seed 580 of ``mixed,bounce,swarm``).  An
        insert is taken: it adds, whatever the others hold."""
        assert self.replicator is not None
        return Response.error(
            Status.SERVICE_UNAVAILABLE,
            "this robot started again and has not heard the other holders yet: a delete or a WHERE would act "
            "without what they hold; not written (try again, or another holder)",
            max_age=max(1, math.ceil(self.replicator.settings.read_after_catch_up_s)),
        )

    async def _repeat(self, tag: WriteTag, ack: Ack, accept: int | None) -> Response | None:
        """The answer to a repeat of a write made under ``tag``'s id (the
        first answer, waited for if it is not given yet), an error if the
        id came with another update; None if the id is new."""
        live = self.live
        made = live.write_ids.get(tag.wid)
        pending = self._answering.get(tag.wid)
        if made is not None:
            digest = made.digest
        elif pending is not None:
            digest = pending[0]
        else:
            return None
        if digest != tag.digest:
            return Response.error(Status.UNPROCESSABLE_ENTITY, (
                f"{WID_PARAM}={tag.wid} was already used for another update (a write's tries carry its id, "
                "each write an id of its own): not written"))
        if pending is not None:
            return await asyncio.shield(pending[1])
        assert made is not None
        if made.answer is not None:
            return made.answer
        return self._from_memory(made, ack, accept)

    async def _answer_once(self, tag: WriteTag, answering: Awaitable[Response]) -> Response:
        """Answer a write made under ``tag`` with ``answering``, which every
        repeat that comes meanwhile awaits too, and keep the answer."""
        live = self.live
        future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
        self._answering[tag.wid] = (tag.digest, future)
        try:
            response = await answering
        except asyncio.CancelledError:
            future.cancel()
            raise
        except BaseException as exc:
            future.set_exception(exc)
            future.exception()  # a repeat waiting gets it; none waiting is no news: this try reports it
            raise
        finally:
            del self._answering[tag.wid]
        made = live.write_ids.get(tag.wid)
        if made is not None:
            made.answer = response
        future.set_result(response)
        return response

    def _from_memory(self, made: Remembered, ack: Ack, accept: int | None) -> Response:
        """A repeat of a write whose answer this robot does not have: one it
        made before it restarted (its data folder kept the write and its id,
        not the answer, nor how far the write had reached: it spreads by
        anti-entropy since), unless no other robot holds these modules; or
        one another holder made and pushed here with its id (the write is on
        two holders at least: that one and this)."""
        if not made.removed and not made.added:
            reached = Reached(Ack.ALL, changed=False)
        elif made.made_by is not None:
            reached = Reached(Ack.TWO, holders=2, made_by=made.made_by)
        else:
            reached = Reached(Ack.ALL if self.replicator is None else Ack.LOCAL, before_restart=True)
        if reached.level.covers(ack):
            return _changed(made.removed, made.added, reached, made.version, accept, durable=True)
        wait_s = 0.0 if self.replicator is None else self.replicator.settings.ack_timeout_s
        return Response.error(Status.GATEWAY_TIMEOUT, short_line(reached, ack, made.version, durable=True,
                                                                 wait_s=wait_s))

    async def _acknowledge(self, written: Written, ack: Ack = DEFAULT_ACK, accept: int | None = None) -> Response:
        """2.04 once the write reached ``ack`` (:mod:`.write_concern`); 5.04
        if it did not within the replicator's ack wait.

        5.04, not 2.04: the writer asked for more than it got, and a 2.04
        read without its payload would promise it.  Nor 5.03, which tells a
        client when to try again: the write is not undone, it spreads on its
        own, and the text says so, with the version it made."""
        live = self.live
        durable = live.keeper is not None
        replicator = self.replicator
        if replicator is not None:
            reached = await replicator.acknowledge(written, ack)
        else:  # no other holder: every holder (this one) has it
            reached = Reached(Ack.ALL, changed=bool(written.deltas))
        if not reached.level.covers(ack):
            assert replicator is not None
            return Response.error(Status.GATEWAY_TIMEOUT, short_line(
                reached, ack, written.version, durable=durable, wait_s=replicator.settings.ack_timeout_s))
        return _changed(written.removed, written.added, reached, written.version, accept, durable=durable)


def _changed(removed: int, added: int, reached: Reached, version: bytes, accept: int | None, *,
             durable: bool) -> Response:
    """A 2.04: its line of text, or for a writer that accepts CBOR (a
    robot's own writes) the ``write-answer`` array, a sixth of the text's
    bytes on every write a robot sends (docs/knowledge.md, "Write concern")."""
    if accept == ContentFormat.CBOR:
        return Response(Status.CHANGED, encode_changed(removed, added, reached), ContentFormat.CBOR, etag=version)
    return Response(Status.CHANGED, changed_line(removed, added, reached, durable=durable).encode(),
                    ContentFormat.TEXT, etag=version)


def _removes(text: str) -> bool:
    """Whether an update may remove, or reads the module to decide what it
    writes (all but INSERT DATA)."""
    return any(op.kind != "INSERT DATA" for op in parse_update(text).operations)


def _not_idempotent(text: str) -> bool:
    """Whether an update may change more when applied again: one that
    matches a pattern (DELETE WHERE only removes, so it may repeat)."""
    return any(op.kind == "MODIFY" for op in parse_update(text).operations)


async def caught_up(replicator: Replicator | None) -> None:
    """Until ``replicator``'s catch-up at start is over (:meth:`.Replicator.caught_up`);
    at once for a KB nobody else holds (None)."""
    if replicator is not None:
        await replicator.caught_up()

"""`RpcServer`: a queryable that answers one request type with one response type.

Runs on a Zenoh thread: decode (validated, rejections counted by reason), call the handler, reply with
the response and a stamped header (source id, sequence number, data stamp, a processing stamp of the
handler's work), or with an `ErrorResponse` when the request is malformed or the handler refuses it.
It never raises into Zenoh and never blocks beyond the handler's own work. A handler may also leave the
request to another server on the same key (`RpcDeclined`: no reply, a sharded coordinator's other
regions) or answer it later without blocking (`RpcDeferred`: the query is kept open and answered when
what it waits for arrives, e.g. a vehicle handed over by another shard).

    server = RpcServer(node, "route_rpc", RouteRequest, handle, stage="coordinator/plan")
    node.queryable(server.key, server)
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar, cast

import zenoh
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse, Header

from shared.bus.codec import MessageDecoder, Rejected, RejectReason, encode
from shared.bus.node import Node, processing_stamp
from shared.bus.streams import get_stream

log = logging.getLogger(__name__)

Req = TypeVar("Req", bound=Message)


class RpcRejected(Exception):
    """Raised by a handler for a request it will not serve: ``rejected/<reason>`` is counted and the
    caller receives an ErrorResponse with ``code`` and ``message``."""

    def __init__(self, reason: str, code: ErrorCode.ValueType, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.code = code
        self.message = message


class RpcDeclined(Exception):
    """Raised by a handler for a request another server on the key answers (`declined/<reason>` is
    counted, nothing is replied: a caller asking every server takes the one that answers)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class RpcDeferred(Exception):
    """Raised by a handler that answers later: `start(resume)` is called at once (on the Zenoh thread: it
    must not block) and must make sure `resume()` is called exactly once, from any thread, when the
    handler can answer; `resume` runs the handler again for the same request and replies. The caller's
    query timeout bounds the wait. A handler that defers again on resume is a bug (INTERNAL)."""

    def __init__(self, start: Callable[[Callable[[], None]], None]) -> None:
        super().__init__("deferred")
        self.start = start


#: ``handle(request, start_ns) -> (response, data stamp in ns or 0)``; may raise RpcRejected,
#: RpcDeclined or RpcDeferred.
Handler = Callable[[Req, int], tuple[Message, int]]


class RpcServer(Generic[Req]):
    """Serve `stream_name` (a queryable stream of `proto/streams.yaml`) with `handle`.

    Parameters
    ----------
    node : Node
        Its counters count ``requests``, the ``served`` ones and ``rejected/<reason>``; its source id is the
        header's.
    stream_name, request_type
        The queryable stream and the protobuf type its requests decode to.
    handle : callable
        See `Handler`. The data stamp (0: none) becomes the header stamp, else the request's arrival.
    stage : str
        Name of the processing stamp added to the header.
    embed_header : callable, optional
        ``embed_header(response, header)`` for responses that also carry the header in their body
        (the header always travels in the attachment).
    served : str
        Counter of the requests answered with a response.
    bind : dict, optional
        Key id -> request field that must equal it (`{"vehicle": "vehicle_id"}`): the queryable serves
        every id of the stream's key, and a request on another id's key is refused (`key_mismatch`), so
        access control on the key confines each identity to its own requests.
    """

    def __init__(
        self,
        node: Node,
        stream_name: str,
        request_type: type[Req],
        handle: Handler[Req],
        *,
        stage: str,
        embed_header: Callable[[Message, Header], None] | None = None,
        served: str = "replies",
        bind: dict[str, str] | None = None,
    ) -> None:
        self.node = node
        stream = get_stream(stream_name)
        self._stream = stream
        self._bind = bind or {}
        self.key = stream.pattern()  # every id a wildcard: one queryable serves them all
        self._qos = stream.qos.publisher_kwargs()
        self._decoder = MessageDecoder(request_type, node.counters)
        self._handle = handle
        self._stage = stage
        self._embed_header = embed_header
        self._served = served
        self._seq_lock = threading.Lock()
        self._seq = 0

    def __call__(self, query: zenoh.Query) -> None:
        start_ns = time.time_ns()
        counters = self.node.counters
        counters.inc("requests")
        try:
            if query.payload is None:
                raise Rejected(RejectReason.DECODE, "query without payload")
            attachment = query.attachment.to_bytes() if query.attachment is not None else None
            decoded = self._decoder.decode_or_raise(query.payload.to_bytes(), str(query.encoding), attachment)
            self._check_key(str(query.key_expr), decoded.message)
        except Rejected as err:
            counters.inc(f"rejected/{err.reason}")
            self._error(query, ErrorCode.ERROR_CODE_INVALID_REQUEST, str(err))
            return
        except RpcRejected as err:
            counters.inc(f"rejected/{err.reason}")
            self._error(query, err.code, err.message)
            return
        self._answer(query, cast(Req, decoded.message), start_ns, resumed=False)

    def _answer(self, query: zenoh.Query, request: Req, start_ns: int, resumed: bool) -> None:
        counters = self.node.counters
        try:
            response, stamp_ns = self._handle(request, start_ns)
        except RpcRejected as err:
            counters.inc(f"rejected/{err.reason}")
            self._error(query, err.code, err.message)
            return
        except RpcDeclined as err:
            counters.inc(f"declined/{err.reason}")
            return
        except RpcDeferred as err:
            if not resumed:
                counters.inc("deferred")
                try:
                    err.start(lambda: self._answer(query, request, start_ns, resumed=True))
                    return
                except Exception:
                    log.exception("%s: deferring failed", self.key)
            counters.inc("rejected/internal")
            self._error(query, ErrorCode.ERROR_CODE_INTERNAL, "internal error")
            return
        except Exception:  # a bug must still answer: the caller gets INTERNAL, not a timeout
            counters.inc("rejected/internal")
            log.exception("%s: handler failed", self.key)
            self._error(query, ErrorCode.ERROR_CODE_INTERNAL, "internal error")
            return
        with self._seq_lock:
            self._seq += 1
            seq = self._seq
        header = Header(source_id=self.node.source_id, seq=seq, frame_id="world")
        header.stamp.FromNanoseconds(stamp_ns or start_ns)
        header.processing.append(processing_stamp(self._stage, start_ns, time.time_ns()))
        if self._embed_header is not None:
            self._embed_header(response, header)
        encoded = encode(response, header)
        try:
            query.reply(
                query.key_expr,
                encoded.payload,
                encoding=encoded.encoding,
                attachment=encoded.attachment,
                **self._qos,
            )
        except Exception as err:  # a deferred answer after the caller's timeout: the query is closed
            counters.inc("reply_failed")
            log.debug("%s: reply failed: %s", self.key, err)
            return
        counters.inc(self._served)

    def _check_key(self, key: str, request: Message) -> None:
        ids = self._stream.ids(key) or {}
        for field, attr in self._bind.items():
            if ids.get(field) != getattr(request, attr):
                raise RpcRejected(
                    "key_mismatch",
                    ErrorCode.ERROR_CODE_INVALID_REQUEST,
                    f"{attr} {getattr(request, attr)!r} asked on {key}",
                )

    @staticmethod
    def _error(query: zenoh.Query, code: ErrorCode.ValueType, message: str) -> None:
        encoded = encode(ErrorResponse(code=code, message=message))
        query.reply_err(encoded.payload, encoding=encoded.encoding)

"""uvicorn's httptools protocol with bounds on what a request may send before the app sees it.

uvicorn bounds the idle time between keep-alive requests but neither the time a client may
take to send its request line and headers nor their size: httptools gathers a header value
in memory however long it grows (an 85 MB header was answered 200). Here, per request:

* the headers must be in within ``seconds`` of the connection opening or of the request's
  first byte (keep-alive, pipelined); otherwise 408 (slow-loris headers);
* the request line's target (path + query) is at most ``max_url_bytes``; otherwise 414;
* at most ``max_headers`` header lines and ``max_header_bytes`` bytes of request line and
  headers; otherwise 431. Bytes are counted as they arrive, so a header without an end
  costs at most the limit plus one read (64 KiB), never the whole header;
* a request the parser refuses (bad syntax, invalid Content-Length) gets 400.

Each of these answers the service's JSON error shape and closes the connection. The body is
bounded separately by the app (``max_body_bytes``, ``request_timeout_s``); the scope's
``vgq.body_complete`` tells the app when the whole body has arrived already (no timer needed
to read it). Writes made in one event-loop step leave in one send (``CoalescingTransport``):
a response's head and body go out together rather than as two TCP segments.
"""

from __future__ import annotations

import asyncio
import os
import time

import httptools
import orjson
from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol

from .body import BODY_COMPLETE

#: uvicorn's ``http=`` option for this protocol (a string, so worker processes can import it)
HTTP = "service.protocol:HeaderTimeoutProtocol"


def error_response(status: int, message: str) -> bytes:
    """A whole HTTP/1.1 response with the service's JSON error body; closes the connection."""
    body = orjson.dumps({"error": {"status": status, "message": message}})
    return STATUS_LINE[
        status
    ] + b"content-type: application/json\r\nconnection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(body), body)


class _Refused(Exception):
    pass


class CoalescingTransport:
    """A connection's transport whose writes within one event-loop step leave together, in one
    ``writelines`` (one send): uvloop sends each ``write`` at once, so a response's head and
    body would be two sends and two wake-ups of the client. Writes keep their order; ``close``
    sends what is pending first, ``abort`` drops it; everything else is the transport's."""

    def __init__(self, transport, loop):
        self._transport, self._loop, self._pending = transport, loop, []

    def write(self, data) -> None:
        if not self._pending:
            self._loop.call_soon(self._flush)
        self._pending.append(data)

    def writelines(self, chunks) -> None:
        for data in chunks:
            self.write(data)

    def _flush(self) -> None:
        pending, self._pending = self._pending, []
        if pending and not self._transport.is_closing():
            self._transport.writelines(pending)

    def close(self) -> None:
        self._flush()
        self._transport.close()

    def abort(self) -> None:
        self._pending = []
        self._transport.abort()

    def __getattr__(self, name):
        return getattr(self._transport, name)


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """The bounds above; worker processes read them from the environment (``VGQ_*``)."""

    seconds: float = float(os.environ.get("VGQ_REQUEST_TIMEOUT_S", "10"))
    max_header_bytes: int = int(os.environ.get("VGQ_MAX_HEADER_BYTES", str(16 * 1024)))
    max_headers: int = int(os.environ.get("VGQ_MAX_HEADERS", "100"))
    max_url_bytes: int = int(os.environ.get("VGQ_MAX_URL_BYTES", str(8 * 1024)))

    _header_timer: asyncio.TimerHandle | None = None
    _in_head = True  # between a request's first byte (or the connection) and its complete headers
    _head_bytes = 0
    _n_headers = 0
    _heads_done = 0
    _fed_counted = 0  # bytes of the current read already counted by the callbacks
    _refusal: tuple[int, str] | None = None

    @classmethod
    def configure(cls, settings) -> None:
        cls.seconds = settings.request_timeout_s
        cls.max_header_bytes, cls.max_headers = settings.max_header_bytes, settings.max_headers
        cls.max_url_bytes = settings.max_url_bytes

    # ---- deadline -------------------------------------------------------------------------
    def _arm(self) -> None:
        if self._header_timer is None:
            self._header_timer = self.loop.call_later(self.seconds, self._headers_late)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        self._refuse(408, f"request headers not received within {self.seconds:g} s")

    def _refuse(self, status: int, message: str) -> None:
        if not self.transport.is_closing():
            self.transport.write(error_response(status, message))
            self.transport.close()

    # ---- size bounds ----------------------------------------------------------------------
    def _count(self, n: int, status: int) -> None:
        self._head_bytes += n
        self._fed_counted += n
        if self._head_bytes > self.max_header_bytes and self._refusal is None:
            self._refusal = (status, f"request line and headers exceed {self.max_header_bytes} bytes")
            raise _Refused

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.transport = CoalescingTransport(transport, self.loop)  # each answer in one send
        self._in_head, self._head_bytes, self._n_headers = True, 0, 0
        self._arm()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head, self._head_bytes, self._n_headers = True, 0, 0
        self._arm()

    def on_url(self, url: bytes) -> None:
        if len(self.url) + len(url) > self.max_url_bytes:
            self._refusal = (414, f"request target exceeds {self.max_url_bytes} bytes")
            raise _Refused
        self._count(len(url), 431)
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._n_headers += 1
        if self._n_headers > self.max_headers:
            self._refusal = (431, f"more than {self.max_headers} request headers")
            raise _Refused
        self._count(len(name) + len(value) + 4, 431)
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        # the request's clock starts here, not when its task first runs: time spent queued behind
        # other requests' work on the event loop counts in the service's latency metrics
        self.scope["vgq.t0"] = time.perf_counter()
        self._disarm()
        self._in_head = False
        self._heads_done += 1
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        self.scope[BODY_COMPLETE] = True  # the whole body is buffered: the app reads it without a timer
        super().on_message_complete()

    def data_received(self, data: bytes) -> None:
        self._unset_keepalive_if_required()
        in_head, heads_done = self._in_head, self._heads_done
        self._fed_counted = 0
        try:
            self.parser.feed_data(data)
        except httptools.HttpParserUpgrade:
            if self._should_upgrade():
                self.handle_websocket_upgrade()
            else:
                self._unsupported_upgrade_warning()
            return
        except (httptools.HttpParserError, _Refused) as e:
            status, message = self._refusal or (400, f"invalid HTTP request: {e}")
            self._refuse(status, message)
            return
        if in_head and self._in_head and heads_done == self._heads_done:
            # the whole read was request line / headers still being gathered by httptools
            self._head_bytes += len(data) - self._fed_counted
            if self._head_bytes > self.max_header_bytes:
                self._refuse(431, f"request line and headers exceed {self.max_header_bytes} bytes")

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

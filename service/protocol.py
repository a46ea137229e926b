"""uvicorn's httptools protocol with a deadline on request headers.

uvicorn bounds the idle time between keep-alive requests but not the time a client may take
to send a request line and its headers: a client that opens a connection and sends nothing,
or half a header block (header slow-loris), would hold it for as long as it likes. Here every
request must have its headers in within ``seconds`` of its connection opening or of its first
byte (a keep-alive or pipelined request); otherwise the service answers 408 and closes.
The body is bounded separately by the app (``request_timeout_s``).
"""

from __future__ import annotations

import asyncio
import os

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

#: uvicorn's ``http=`` option for this protocol (a string, so worker processes can import it)
HTTP = "service.protocol:HeaderTimeoutProtocol"


class HeaderTimeoutProtocol(HttpToolsProtocol):
    """Closes a connection with 408 when a request's headers take longer than ``seconds``
    (the service's ``request_timeout_s``; worker processes read it from the environment)."""

    seconds: float = float(os.environ.get("VGQ_REQUEST_TIMEOUT_S", "10"))
    _header_timer: asyncio.TimerHandle | None = None

    def _arm(self) -> None:
        if self._header_timer is None:
            self._header_timer = self.loop.call_later(self.seconds, self._headers_late)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        if not self.transport.is_closing():
            body = f"request headers not received within {self.seconds:g} s".encode()
            self.transport.write(b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
                                 b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(body), body))
            self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm()

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

"""Read a request body into memory within the service's bounds: ``max_body_bytes`` (413),
``request_timeout_s`` (408), the shared byte budget (503 + Retry-After, see service.limits).
A client that disconnects mid-body raises ClientGone (counted as 499, never a 500)."""

from __future__ import annotations

import asyncio

from starlette.requests import ClientDisconnect, Request

from .errors import ApiError
from .limits import CLIENT_GONE, RETRY_AFTER_S

CLOSE = {"connection": "close"}  # the rest of an unread body is not worth reading
#: scope key set by service.protocol once the server has received the request's whole body
BODY_COMPLETE = "vgq.body_complete"
_timeout = getattr(asyncio, "timeout", None)


class ClientGone(ApiError):
    def __init__(self, when: str = "before the request body was received"):
        super().__init__(CLIENT_GONE, f"client disconnected {when}")


def _over_budget(n: int) -> ApiError:
    return ApiError(
        503,
        f"the service holds its limit of request bodies in memory; {n} more bytes do not fit, retry shortly",
        headers={"retry-after": str(RETRY_AFTER_S), **CLOSE},
    )


async def _chunk(receive) -> tuple[bytes, bool]:
    """The next body chunk of an ASGI request and whether more follow (Starlette's
    ``Request.stream`` without a Request or an async generator); ClientDisconnect when the
    client went away first."""
    message = await receive()
    if message["type"] == "http.request":
        return message.get("body", b""), message.get("more_body", False)
    if message["type"] == "http.disconnect":
        raise ClientDisconnect()
    return b"", True  # no other message type carries a body


async def _read(receive, limit: int, length: int | None, reservation):
    more = True
    if length is not None:
        buf, pos = bytearray(length), 0  # one buffer of the declared size: no list of chunks, no join
        while more:
            c, more = await _chunk(receive)
            if pos + len(c) > length:
                raise ApiError(400, "request body longer than its Content-Length", headers=CLOSE)
            buf[pos : pos + len(c)] = c
            pos += len(c)
        if pos != length:
            raise ClientGone()
        return buf
    parts, n = [], 0
    while more:
        c, more = await _chunk(receive)
        if not c:
            continue
        n += len(c)
        if n > limit:
            raise ApiError(413, f"request body exceeds the limit of {limit} bytes", headers=CLOSE)
        if reservation is not None and not reservation.take(len(c)):
            raise _over_budget(len(c))
        parts.append(c)
    return b"".join(parts)


async def read_body(request: Request, max_body_bytes: int, timeout_s: float) -> bytes | bytearray:
    """The whole body (bytes or bytearray); raises ApiError 400 / 408 / 413 / 503 or ClientGone."""
    scope = request.scope
    return await read_asgi_body(
        request.receive,
        request.headers.get("content-length"),
        scope.get("vgq.reservation"),
        max_body_bytes,
        timeout_s,
        scope.get(BODY_COMPLETE, False),
    )


async def read_asgi_body(
    receive, content_length: str | None, reservation, max_body_bytes: int, timeout_s: float, complete: bool = False
) -> bytes | bytearray:
    """:func:`read_body` from an ASGI ``receive``, given the request's Content-Length header
    (None when absent) and its byte-budget reservation (None: none). ``complete``: the server
    holds the whole body already (the scope's BODY_COMPLETE), so reading it cannot wait and no
    timer is armed (a timer costs more than the read)."""
    length = None
    if content_length is not None:
        if not content_length.isdigit() or len(content_length) > 19:
            raise ApiError(400, "invalid Content-Length header", headers=CLOSE)
        length = int(content_length)
        if length > max_body_bytes:
            raise ApiError(
                413, f"request body of {length} bytes exceeds the limit of {max_body_bytes} bytes", headers=CLOSE
            )
    if length and reservation is not None and not reservation.take(length):
        raise _over_budget(length)
    try:
        if complete:
            return await _read(receive, max_body_bytes, length, reservation)
        if _timeout is not None:  # asyncio.timeout (3.11+): no extra task per request, unlike wait_for
            async with _timeout(timeout_s):
                return await _read(receive, max_body_bytes, length, reservation)
        return await asyncio.wait_for(_read(receive, max_body_bytes, length, reservation), timeout_s)
    except asyncio.TimeoutError:
        raise ApiError(408, f"request body not received within {timeout_s} s", headers=CLOSE) from None
    except ClientDisconnect:
        raise ClientGone() from None

"""Read a request body into memory within the service's bounds: ``max_body_bytes`` (413),
``request_timeout_s`` (408), the shared byte budget (503 + Retry-After, see service.limits).
A client that disconnects mid-body raises ClientGone (counted as 499, never a 500)."""

from __future__ import annotations

import asyncio

from starlette.requests import ClientDisconnect, Request

from .errors import ApiError
from .limits import CLIENT_GONE, RETRY_AFTER_S

CLOSE = {"connection": "close"}  # the rest of an unread body is not worth reading
_timeout = getattr(asyncio, "timeout", None)


class ClientGone(ApiError):
    def __init__(self):
        super().__init__(CLIENT_GONE, "client disconnected before the request body was received")


def _over_budget(n: int) -> ApiError:
    return ApiError(
        503,
        f"the service holds its limit of request bodies in memory; {n} more bytes do not fit, retry shortly",
        headers={"retry-after": str(RETRY_AFTER_S), **CLOSE},
    )


async def _read(request: Request, limit: int, length: int | None, reservation):
    if length is not None:
        buf, pos = bytearray(length), 0  # one buffer of the declared size: no list of chunks, no join
        async for c in request.stream():
            if pos + len(c) > length:
                raise ApiError(400, "request body longer than its Content-Length", headers=CLOSE)
            buf[pos : pos + len(c)] = c
            pos += len(c)
        if pos != length:
            raise ClientGone()
        return buf
    chunks, n = [], 0
    async for c in request.stream():
        n += len(c)
        if n > limit:
            raise ApiError(413, f"request body exceeds the limit of {limit} bytes", headers=CLOSE)
        if reservation is not None and not reservation.take(len(c)):
            raise _over_budget(len(c))
        chunks.append(c)
    return b"".join(chunks)


async def read_body(request: Request, max_body_bytes: int, timeout_s: float) -> bytes | bytearray:
    """The whole body (bytes or bytearray); raises ApiError 400 / 408 / 413 / 503 or ClientGone."""
    cl = request.headers.get("content-length")
    length = None
    if cl is not None:
        if not cl.isdigit() or len(cl) > 19:
            raise ApiError(400, "invalid Content-Length header", headers=CLOSE)
        length = int(cl)
        if length > max_body_bytes:
            raise ApiError(
                413, f"request body of {length} bytes exceeds the limit of {max_body_bytes} bytes", headers=CLOSE
            )
    reservation = request.scope.get("vgq.reservation")
    if length and reservation is not None and not reservation.take(length):
        raise _over_budget(length)
    try:
        if _timeout is not None:  # asyncio.timeout (3.11+): no extra task per request, unlike wait_for
            async with _timeout(timeout_s):
                return await _read(request, max_body_bytes, length, reservation)
        return await asyncio.wait_for(_read(request, max_body_bytes, length, reservation), timeout_s)
    except asyncio.TimeoutError:
        raise ApiError(408, f"request body not received within {timeout_s} s", headers=CLOSE) from None
    except ClientDisconnect:
        raise ClientGone() from None

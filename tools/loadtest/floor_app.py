"""The HTTP floor: an ASGI app that reads a request's whole body and answers ``x-answer-bytes``
bytes, nothing else (no parsing, model, cache or metrics). ``tools.loadtest.overhead`` runs it on
the service's uvicorn stack (uvloop, httptools) to show what uvicorn itself costs per call:

    python -m uvicorn tools.loadtest.floor_app:app --loop uvloop --http httptools --port 8001
"""

from __future__ import annotations


async def app(scope, receive, send) -> None:
    if scope["type"] == "lifespan":
        await receive()  # lifespan.startup
        await send({"type": "lifespan.startup.complete"})
        await receive()  # lifespan.shutdown
        await send({"type": "lifespan.shutdown.complete"})
        return
    size = 0
    for name, value in scope["headers"]:
        if name == b"x-answer-bytes":
            size = int(value)
    chunks, more = [], True
    while more:  # the body, read and kept as an app would (joined once)
        message = await receive()
        chunks.append(message.get("body", b""))
        more = message.get("more_body", False)
    b"".join(chunks)
    headers = [(b"content-type", b"application/octet-stream"), (b"content-length", b"%d" % size)]
    await send({"type": "http.response.start", "status": 200, "headers": headers})
    await send({"type": "http.response.body", "body": bytes(size)})

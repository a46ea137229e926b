"""HTTP load test of a running scoring service (asyncio + httpx; no torch, no service import).

    python -m tools.loadtest --url http://127.0.0.1:8000 --clients 8 --duration 30 --k 128
    python -m tools.loadtest --clients 1 --duration 20          # sequential latency (raw client)
    locust -f tools/loadtest/locustfile.py --host http://127.0.0.1:8000   # for teams on Locust

N clients run concurrently for a bounded time. Each repeats a cycle (``--mix``, default
``upload=1,score=8,once=1``): upload a fresh depth image (``POST /v1/images``, encoder runs),
score k grasps against it several times (``POST /v1/images/{id}/scores``, cached image, head
only; float32 body and answer, as ``service.client`` sends), then one-shot calls with fresh
images (``POST /v1/score``, .npz body, uncached: encoder + head), then (``bad=N``) malformed
requests in rotation, each of which must get a 4xx with an error message (soak runs). Images
are the example in ``examples/`` (or a synthetic table + box scene) with a unique value written
into pixel (0, 0), outside the crop window, so every upload is a cache miss.

Reports per endpoint the requests, errors, p50 / p90 / p99 / max latency (client side, ms),
the server-side mean (from the service's /metrics, when readable), requests and grasps per
second, and with ``--server-pid`` the server's resident memory (process and its children)
before and after. It only targets the URL given and refuses non-loopback hosts unless
``--allow-remote`` is passed.

Modules: ``workload`` (what is sent), ``client`` (who sends it), ``report`` (what is measured),
``cli`` (the command line), ``locustfile`` (the same cycle as Locust users).
"""

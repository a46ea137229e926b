"""``vgq-serve`` / ``python -m service``: run the scoring service with uvicorn."""

from __future__ import annotations

import os
import sys

from .config import Settings, parse_args


def build_app():
    """uvicorn factory (used with --workers > 1): settings come from VGQ_* variables.

    Each worker loads its model before it accepts a connection (uvicorn runs the lifespan
    first): with a background load, a worker still loading would take its share of the
    connections and answer 503 while another already answers /readyz 200. Connections made
    meanwhile wait in the shared socket's backlog for a worker that is ready."""
    from .app import create_app
    from .config import from_env

    return create_app(from_env(), load_in_background=False)


def main(argv=None) -> None:
    import uvicorn

    from .protocol import HTTP, HeaderTimeoutProtocol

    s: Settings = parse_args(argv)
    HeaderTimeoutProtocol.configure(s)
    if not os.path.isdir(s.model_dir):
        print(
            f"vgq-serve: model folder {s.model_dir!r} does not exist (set --model-dir or VGQ_MODEL_DIR)",
            file=sys.stderr,
        )
        sys.exit(2)
    common = dict(
        host=s.host,
        port=s.port,
        log_level=s.log_level,
        access_log=False,
        loop="uvloop",
        http=HTTP,
        timeout_keep_alive=30,
    )
    if s.workers > 1:
        # each worker builds its own app from the environment: pass the settings through it
        for k, v in vars(s).items():
            os.environ[f"VGQ_{k.upper()}"] = str(v)
        uvicorn.run("service.__main__:build_app", factory=True, workers=s.workers, **common)
    else:
        from .app import create_app

        uvicorn.run(create_app(s), **common)


if __name__ == "__main__":
    main()

"""Moved: the load test is now its own package, ``tools.loadtest`` (``python -m tools.loadtest``).

This shim keeps ``python -m service.loadtest`` working for existing scripts; the service
itself does not use it.
"""

from tools.loadtest.cli import main  # noqa: F401
from tools.loadtest.client import check_target, run_load  # noqa: F401
from tools.loadtest.report import server_latency_totals, server_rss_bytes, summarize, table  # noqa: F401
from tools.loadtest.workload import Mix, Workload, load_workload  # noqa: F401

if __name__ == "__main__":
    main()

"""Developer and operator tools that are not part of the service (load test, ...)."""

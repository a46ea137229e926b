"""One pytest test per OpenAPI operation, for the schemathesis suites.

``schema.parametrize()`` over a whole schema gives all its items one node id
(``file::test``), and pytest-xdist schedules by node id: the parallel suite ran one
operation of ten. Here each operation gets a test function of its own name, running
schemathesis' full run of that operation (its phases, valid and invalid data,
undocumented methods) exactly as ``parametrize()`` would."""

from __future__ import annotations

import re
from collections.abc import Callable, MutableMapping

from hypothesis import HealthCheck, settings


def add_operation_tests(
    namespace: MutableMapping, prefix: str, schema, max_examples: int, check: Callable[[object, str, str], None]
) -> list[str]:
    """Add ``prefix + method_path`` tests to ``namespace`` (a module's ``globals()``): each runs
    ``check(case, url, image_id)`` (url and image_id: the module's fixtures) on the cases
    schemathesis draws for one operation, ``max_examples`` per phase, derandomised (the same
    cases every run), no deadline. Returns the names added, in the schema's order."""
    names = []
    for op in (r.ok() for r in schema.get_all_operations()):
        name = prefix + re.sub(r"\W+", "_", f"{op.method} {op.path}".lower()).strip("_")
        namespace[name] = _operation_test(schema, op.method.upper(), op.path, max_examples, check)
        names.append(name)
    return names


def _operation_test(schema, method: str, path: str, max_examples: int, check):
    @schema.include(method=method, path=path).parametrize()
    @settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    def test(case, url, image_id):
        check(case, url, image_id)

    return test

"""Test-run wiring: how `make test` spreads the tests over the cores (pytest-xdist, ``-n auto
--dist loadfile``).

Every test module stays whole on one worker (its module-scoped fixtures are made once). The
multi-process tests (tests/integration: a router, a server and agents on loopback, timed in
seconds) are one unit: they run one after another on one worker, so no two of them share the
cores at once, and first, since together they are the longest unit.
(xdist's own ``--dist loadgroup`` would say this with marks, but it names the groups by rewriting
node ids, which pytest 9.2 no longer lets it do.)
"""

from __future__ import annotations

import pytest

INTEGRATION = "tests/integration/"


def _unit(nodeid: str) -> str:
    path = nodeid.split("::", 1)[0]
    return INTEGRATION if path.startswith(INTEGRATION) else path


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: not item.nodeid.startswith(INTEGRATION))  # (stable: else as collected)


@pytest.hookimpl(optionalhook=True)  # (xdist may be absent: a plain `pytest` run)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class Units(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _unit(nodeid)

    return Units(config, log)

"""Faults an unlucky or hostile operator hits, each as the operator hit it (issue 24's table):
real processes on loopback where the fault needs them."""

from __future__ import annotations

import time

import pytest

from fleet_slam.procs import ProcGroup, python_module
from tests.netutil import loopback_endpoint

pytestmark = pytest.mark.integration

STARTUP_S = 30.0


def test_row2_a_second_server_on_the_same_state_exits_2_at_once_naming_the_holder(tmp_path):
    """Two servers on one ``--state``: the second exits 2 at once with a message naming the
    directory and the holder; the first keeps running and saving."""
    endpoint = loopback_endpoint()
    state = tmp_path / "state"
    with ProcGroup(tmp_path / "logs") as group:
        router = group.start("router", python_module("shared.bus", "router", "--listen", endpoint))
        assert router.wait_for("listening", STARTUP_S), router.output()
        argv = ["--connect", endpoint, "--state", state]
        first = group.start("server1", python_module("map_server", *argv))
        assert first.wait_for("running", STARTUP_S), first.output()
        t0 = time.monotonic()
        second = group.start("server2", python_module("map_server", *argv))
        code = second.popen.wait(timeout=STARTUP_S)
        took = time.monotonic() - t0
        out = second.output()
        assert code == 2, out
        assert str(state) in out and "in use" in out and f"pid {first.popen.pid}" in out, out
        assert took < 10.0  # at once: before it connects anywhere (the interpreter's start-up)
        time.sleep(1.0)
        assert first.running, first.output()

"""A service waiting for its router stops on SIGTERM with a message and exit 130, not a traceback."""

import os
import signal
import subprocess
import sys
import time

import pytest

from fleet_slam.procs import free_port


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "command",
    [["fleet_slam.cli", "server"], ["fleet_slam.cli", "subscribe"], ["map_server"], ["robot_agent"]],
)
def test_sigterm_while_waiting_for_the_router(command):
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there
    extra = ["--robot", "robot1", "--world", "office"] if command == ["robot_agent"] else []
    proc = subprocess.Popen(
        [sys.executable, "-m", *command, "--connect", endpoint, *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        time.sleep(2.0)  # inside zenoh.open's wait for the router
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err and "cancelled while waiting" in err, err


@pytest.mark.timeout(60)
def test_a_process_group_stops_its_children_when_its_parent_gets_sigterm(tmp_path):
    """``fleet-slam demo`` (and the benchmarks) start a router, a server and agents in a
    ProcGroup: a SIGTERM to the parent (a supervisor's stop, a CI timeout) stops them too, as the
    end of its ``with`` block does, rather than leaving them running."""
    script = (
        "import sys, time\n"
        "from fleet_slam.procs import ProcGroup\n"
        f"with ProcGroup({str(tmp_path)!r}) as g:\n"
        "    child = g.start('child', [sys.executable, '-c', 'import time; time.sleep(120)'])\n"
        "    print(child.popen.pid, flush=True)\n"
        "    time.sleep(120)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    child = None
    try:
        child = int(proc.stdout.readline())
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        gone = False
        for _ in range(100):
            try:
                os.kill(child, 0)
            except ProcessLookupError:
                gone = True
                break
            time.sleep(0.1)
        assert gone, "the child outlived its parent's SIGTERM"
        assert proc.returncode == 128 + signal.SIGTERM
    finally:
        for pid in (proc.pid, child):
            if pid is not None:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        proc.wait()

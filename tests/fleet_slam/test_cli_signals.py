"""A service waiting for its router stops on SIGTERM with a message and exit 130, not a traceback."""

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

"""Child processes with their own handles: started with output to a log file, stopped by handle
(SIGTERM, then SIGKILL after a grace period), never left behind."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

STOP_GRACE_S = 10.0


def free_port() -> int:
    """A TCP port on 127.0.0.1 free right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen
    log_path: Path

    @property
    def running(self) -> bool:
        return self.popen.poll() is None

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def wait_for(self, text: str, timeout_s: float) -> bool:
        """True once ``text`` appears in the output; False on timeout or if the process ended."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if text in self.output():
                return True
            if not self.running:
                return text in self.output()
            time.sleep(0.05)
        return False

    def stop(self, grace_s: float = STOP_GRACE_S) -> int:
        """SIGTERM, wait up to ``grace_s``, then SIGKILL; returns the exit code."""
        if self.running:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(grace_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
        return self.popen.wait()

    def kill(self) -> int:
        """SIGKILL now (a crash)."""
        if self.running:
            self.popen.kill()
        return self.popen.wait()


def python_module(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *map(str, args)]


def start(name: str, argv: list[str], log_dir: str | Path, env: dict | None = None) -> Proc:
    """Start ``argv`` with stdout and stderr to ``log_dir/<name>.log``."""
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"{name}.log"
    full_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    with open(log_path, "ab") as f:
        popen = subprocess.Popen(
            argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=full_env
        )
    return Proc(name, popen, log_path)


def _terminated(signum, frame) -> None:
    raise SystemExit(128 + signum)


class ProcGroup:
    """Processes stopped together (reverse start order) when the ``with`` block ends, however —
    a SIGTERM to this process included: while a group is open in the main thread, SIGTERM
    (default: die at once, every child left running) raises SystemExit(143) there instead, so the
    block ends and stops them. A handler someone else installed is left alone."""

    def __init__(self, log_dir: str | Path):
        self.log_dir = Path(log_dir)
        self.procs: list[Proc] = []
        self._sigterm = None  # the handler before ours (ours installed: not None)

    def start(self, name: str, argv: list[str], env: dict | None = None) -> Proc:
        p = start(name, argv, self.log_dir, env)
        self.procs.append(p)
        return p

    def stop_all(self) -> None:
        for p in reversed(self.procs):
            p.stop()

    def __enter__(self) -> ProcGroup:
        main = threading.current_thread() is threading.main_thread()
        if main and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            self._sigterm = signal.signal(signal.SIGTERM, _terminated)
        return self

    def __exit__(self, *exc) -> None:
        if self._sigterm is not None:  # (a second SIGTERM does not cut the stopping short)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            self.stop_all()
        finally:
            if self._sigterm is not None:
                signal.signal(signal.SIGTERM, self._sigterm)
                self._sigterm = None

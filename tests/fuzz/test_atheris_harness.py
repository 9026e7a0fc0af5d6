"""The atheris harness runs (a short smoke run of each target) where atheris is installed; the
hypothesis tests are the fuzzing of ``make test``, this is the longer optional run's entry point."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("atheris", reason="atheris is optional (pip install atheris): the longer fuzz run")

HARNESS = Path(__file__).with_name("fuzz_decoders.py")


@pytest.mark.parametrize("target", ["wire", "carmen", "server"])
def test_harness_smoke_run(target, tmp_path):
    done = subprocess.run(
        [sys.executable, str(HARNESS), target, "-atheris_runs=2000"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Done 2000" in done.stderr
    assert not list(tmp_path.glob("crash-*"))

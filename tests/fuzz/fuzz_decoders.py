"""Coverage-guided fuzzing of every decoder with atheris: the longer, optional run beside the
hypothesis tests of ``make test`` (same properties, inputs mutated towards new code paths).

atheris is a native extension and no dev dependency: ``pip install atheris`` first. Then::

    python tests/fuzz/fuzz_decoders.py wire   [-atheris_runs=N] [-max_total_time=S] [CORPUS_DIR ...]
    python tests/fuzz/fuzz_decoders.py carmen ...
    python tests/fuzz/fuzz_decoders.py server ...

Without a corpus directory a temporary one is seeded with valid inputs (encoded messages, CARMEN
lines). A failing input is written by libFuzzer as ``crash-<sha1>`` in the working directory;
replay it with the same command and the file as the only argument.

- ``wire``: ``codec.decode`` / ``decode_stored_map`` return a valid message (that encodes again)
  or raise ``WireFormatError`` — never the codec's defensive catch-all (``codec.UNEXPECTED``);
- ``carmen``: ``read_log`` returns a LaserLog with finite derived values or raises
  ``LogFormatError`` naming the line;
- ``server``: ``MapServer.on_map`` / ``on_pose`` either take a message or count a rejection —
  nothing else escapes, and a tick after any input does not raise.
"""

from __future__ import annotations

import gzip
import os
import sys
import tempfile
from pathlib import Path

import atheris

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

with atheris.instrument_imports(include=["shared", "robot_agent", "map_server"]):
    import numpy as np

    from map_server.server import MapServer
    from robot_agent.sources.carmen import LogFormatError, read_log
    from shared import codec
    from shared.keys import Keys
    from shared.messages import WireFormatError

KEYS = Keys()
_LOG = Path(tempfile.mkdtemp(prefix="fuzz_carmen_")) / "log.clf"


def fuzz_wire(data: bytes) -> None:
    for decode in (codec.decode, codec.decode_stored_map):
        try:
            msg = decode(data)
        except WireFormatError as e:
            assert codec.UNEXPECTED not in str(e), str(e)
            continue
        again = (
            codec.decode(codec.encode(msg))
            if decode is codec.decode
            else codec.decode_stored_map(codec.encode_stored_map(msg))
        )
        assert type(again) is type(msg)


def fuzz_carmen(data: bytes) -> None:
    _LOG.write_bytes(data)
    try:
        log = read_log(_LOG, progress=False)
    except LogFormatError as e:
        first = 0 if e.message_type == "log" else 1  # "no laser lines": the last line, 0 if empty
        assert e.line_no >= first and e.field and e.problem and len(str(e)) < 300 + len(str(_LOG)), str(e)
        return
    for name in ("stamps_s", "odometry", "laser_offset", "odom_poses"):
        assert np.all(np.isfinite(getattr(log, name))), name
    assert all(np.all(np.isfinite(scan.angles_rad)) for scan in log.scans())
    assert np.isfinite(log.range_max_m) and log.range_max_m > 0


class _NoBus:
    def put(self, key, payload, reliable=True):
        pass

    def get(self, key_expr, timeout_s=2.0):
        return []


def fuzz_server(data: bytes) -> None:
    server = MapServer(_NoBus(), KEYS)
    server.now_s = lambda: 1.0
    fdp = atheris.FuzzedDataProvider(data)
    calls = 0
    while fdp.remaining_bytes():
        robot = ("robot1", "robot2")[fdp.ConsumeIntInRange(0, 1)]
        payload = fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 4096))
        if fdp.ConsumeBool():
            server.on_map(KEYS.robot_map(robot), payload)
        else:
            server.on_pose(KEYS.robot_pose(robot), payload)
        calls += 1
    assert sum(server.rejected.values()) + sum(server.received.values()) == calls
    server.tick()


def seeds() -> list[bytes]:
    from tests.shared.test_codec import samples  # valid messages of every kind

    intel = gzip.decompress((ROOT / "tests" / "data" / "intel_head.clf.gz").read_bytes())
    head = b"\n".join(intel.splitlines()[:40]) + b"\n"
    return [*samples(), head, b"FLASER 3 1 2 3 0 0 0 0 0 0 100.5 nohost 0.1\n"]


TARGETS = {"wire": fuzz_wire, "carmen": fuzz_carmen, "server": fuzz_server}


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in TARGETS:
        sys.exit(f"usage: {sys.argv[0]} {{{','.join(TARGETS)}}} [libFuzzer options] [CORPUS_DIR ...]")
    target, argv = TARGETS[sys.argv[1]], [sys.argv[0], *sys.argv[2:]]
    if not any(not a.startswith("-") for a in argv[1:]):  # no corpus or input given: a seeded one
        corpus = tempfile.mkdtemp(prefix=f"fuzz_{sys.argv[1]}_")
        for i, seed in enumerate(seeds()):
            Path(corpus, f"seed{i}").write_bytes(seed)
        argv.append(corpus)
    os.environ.setdefault("PYTHONHASHSEED", "0")
    atheris.Setup(argv, target)
    atheris.Fuzz()


if __name__ == "__main__":
    main()

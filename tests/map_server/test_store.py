"""The durable state: atomic, verified, and a damaged state is reported, never loaded."""

import json
import os

import pytest

from map_server.store import StateError, Store


def test_round_trip_and_none_when_empty(tmp_path):
    s = Store(tmp_path / "state")
    assert s.load() is None
    s.save({"version": 3, "robots": ["a", "b"]}, {"a": b"\x00\x01map-a", "b": b"map-b"})
    meta, blobs = Store(tmp_path / "state").load()
    assert meta == {"version": 3, "robots": ["a", "b"]}
    assert blobs == {"a": b"\x00\x01map-a", "b": b"map-b"}


def test_the_index_is_the_canonical_document_with_its_checksum(tmp_path):
    """The index is written from the body's text with the checksum appended (one encoding): the
    same bytes as encoding the whole document, keys sorted, and what load() verifies."""
    import hashlib

    meta = {"z": [1.5, -2.25e-7, 3], "a": {"k": "é", "n": None}, "robots": {"r2": 1, "r1": 2}}
    s = Store(tmp_path)
    s.save(meta, {"b": b"two", "a": b"one"})
    blobs = {"a": hashlib.sha256(b"one").hexdigest(), "b": hashlib.sha256(b"two").hexdigest()}
    body = {"format": 1, "meta": meta, "blobs": blobs}

    def canonical(obj):
        return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()

    doc = dict(body, sha256=hashlib.sha256(canonical(body)).hexdigest())
    assert (tmp_path / "state.json").read_bytes() == canonical(doc)
    assert s.load() == (meta, {"a": b"one", "b": b"two"})


def test_old_blobs_are_removed_and_shared_blobs_kept(tmp_path):
    s = Store(tmp_path)
    s.save({}, {"a": b"one", "b": b"two"})
    s.save({}, {"a": b"one", "c": b"three"})
    assert sorted(p.read_bytes() for p in (tmp_path / "blobs").glob("*.bin")) == [b"one", b"three"]
    assert s.load()[1] == {"a": b"one", "c": b"three"}


def test_tampered_index_is_detected(tmp_path):
    s = Store(tmp_path)
    s.save({"version": 1}, {"a": b"x"})
    doc = json.loads(s.index.read_text())
    doc["meta"]["version"] = 2
    s.index.write_text(json.dumps(doc))
    with pytest.raises(StateError, match="checksum mismatch"):
        s.load()


@pytest.mark.parametrize("content", [b"", b"{not json", b"[1, 2]", b'{"format": 1}'])
def test_garbage_index_is_reported(tmp_path, content):
    s = Store(tmp_path)
    s.save({}, {})
    s.index.write_bytes(content)
    with pytest.raises(StateError, match=r"state\.json"):
        s.load()


def test_damaged_or_missing_blob_is_reported(tmp_path):
    s = Store(tmp_path)
    s.save({}, {"robot1": b"payload"})
    (blob,) = (tmp_path / "blobs").glob("*.bin")
    blob.write_bytes(b"payloaX")
    with pytest.raises(StateError, match=r"robot1.*checksum"):
        s.load()
    blob.unlink()
    with pytest.raises(StateError, match=r"robot1.*missing"):
        s.load()


def test_unknown_format_is_reported(tmp_path):
    s = Store(tmp_path)
    s.save({}, {})
    doc = json.loads(s.index.read_text())
    doc["format"] = 99
    s.index.write_text(json.dumps(doc))
    with pytest.raises(StateError, match="format 99"):
        s.load()


def test_a_crash_before_the_index_is_replaced_leaves_the_old_state(tmp_path, monkeypatch):
    s = Store(tmp_path)
    s.save({"v": 1}, {"a": b"old"})
    import map_server.store as store_mod

    real = store_mod._atomic_write

    def crash_on_index(path, data, **kw):
        if path.name == "state.json":
            raise OSError("simulated crash")
        real(path, data, **kw)

    monkeypatch.setattr(store_mod, "_atomic_write", crash_on_index)
    with pytest.raises(OSError, match="simulated crash"):
        s.save({"v": 2}, {"a": b"new"})
    monkeypatch.undo()
    assert Store(tmp_path).load() == ({"v": 1}, {"a": b"old"})


def test_temp_files_left_by_a_crash_are_ignored_then_removed(tmp_path):
    s = Store(tmp_path)
    s.save({"v": 1}, {"a": b"one"})
    left = [tmp_path / ".state.json.x1.tmp", tmp_path / "blobs" / ".abc.bin.x2.tmp"]
    for path in left:
        path.write_bytes(b"{half a wri")  # what a kill -9 mid-write leaves
    assert s.load() == ({"v": 1}, {"a": b"one"})
    s.save({"v": 2}, {"a": b"two"})
    assert not any(path.exists() for path in left)
    assert Store(tmp_path).load() == ({"v": 2}, {"a": b"two"})


SAVER = """
import sys, numpy as np
from map_server.store import Store
s, rng = Store(sys.argv[1]), np.random.default_rng(int(sys.argv[2]))
v = (s.load() or ({"v": 0}, {}))[0]["v"]
print("saving", v, flush=True)
while True:
    v += 1
    s.save({"v": v}, {f"r{i}": rng.bytes(int(rng.integers(1, 400_000))) for i in range(3)})
"""


def test_kill_9_at_random_moments_while_saving_never_leaves_a_half_written_state(tmp_path):
    """A process saving in a loop (about 0.6 MB a save, each save resuming from the last) is
    killed with SIGKILL at a random moment, over and over: every time the state loads, verified,
    at a version no older than the one the killed process started from."""
    import subprocess
    import sys
    import time

    import numpy as np

    rng = np.random.default_rng(0)
    last, mid_write = 0, 0
    for k in range(12):
        proc = subprocess.Popen(
            [sys.executable, "-c", SAVER, str(tmp_path), str(k)], stdout=subprocess.PIPE, text=True
        )
        try:
            assert proc.stdout.readline().split() == ["saving", str(last)]
            time.sleep(float(rng.uniform(0.05, 0.4)))
        finally:
            proc.kill()
            proc.wait()
            proc.stdout.close()
        mid_write += any(tmp_path.rglob(".*.tmp"))  # killed while writing a file
        meta, blobs = Store(tmp_path).load()  # StateError if anything were half-written
        assert set(blobs) == {"r0", "r1", "r2"} and meta["v"] >= last
        last = meta["v"]
    assert last > 12  # it did save between the kills
    assert mid_write >= 1  # and kills did land mid-write (measured 5-8 of 12)


def test_opening_a_damaged_state_reports_it_at_once(tmp_path):
    Store(tmp_path).save({"v": 1}, {"a": b"x"})
    (tmp_path / "state.json").write_bytes(b'{"format": 1, "me')
    with pytest.raises(StateError, match=r"state\.json: not valid JSON"):
        Store(tmp_path)
    assert Store(tmp_path, check=False).index.exists()  # opened unchecked: nothing read yet


def test_a_state_directory_has_one_owner(tmp_path):
    """The lock names its holder; a second one is refused naming the directory and the holder;
    released, the next takes it; a holder named in the file without the lock held (killed) is
    reported as stale and taken over."""
    from map_server.store import StateLock

    first = StateLock(tmp_path)
    assert first.stale is None
    with pytest.raises(StateError, match=rf"{tmp_path}: state directory in use by pid {os.getpid()} on "):
        StateLock(tmp_path)
    first.release()
    assert (tmp_path / "lock").read_text() == ""  # released cleanly: no name left
    with StateLock(tmp_path) as again:
        assert again.stale is None
    (tmp_path / "lock").write_text("pid 999999 on robot-host since 2026-01-01T00:00:00Z\n")
    taken = StateLock(tmp_path)
    assert taken.stale == "pid 999999 on robot-host since 2026-01-01T00:00:00Z"
    taken.release()


def test_temp_files_of_a_live_writer_are_left_alone(tmp_path):
    """A save deletes the temp files of writers that are gone (a crash mid-write), never those of
    a process still running."""
    import subprocess
    import sys

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        s = Store(tmp_path)
        s.save({"v": 1}, {"a": b"x"})
        theirs = tmp_path / f".state.json.{live.pid}.abc.tmp"
        dead = tmp_path / ".state.json.999999.abc.tmp"
        mine = tmp_path / "blobs" / f".x.bin.{os.getpid()}.abc.tmp"
        for path in (theirs, dead, mine):
            path.write_bytes(b"half")
        s.save({"v": 2}, {"a": b"y"})
        assert theirs.exists() and not dead.exists() and not mine.exists()
    finally:
        live.kill()
        live.wait()

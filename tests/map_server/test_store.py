"""The durable state: atomic, verified, and a damaged state is reported, never loaded."""

import json

import pytest

from map_server.store import StateError, Store


def test_round_trip_and_none_when_empty(tmp_path):
    s = Store(tmp_path / "state")
    assert s.load() is None
    s.save({"version": 3, "robots": ["a", "b"]}, {"a": b"\x00\x01map-a", "b": b"map-b"})
    meta, blobs = Store(tmp_path / "state").load()
    assert meta == {"version": 3, "robots": ["a", "b"]}
    assert blobs == {"a": b"\x00\x01map-a", "b": b"map-b"}


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

    def crash_on_index(path, data):
        if path.name == "state.json":
            raise OSError("simulated crash")
        real(path, data)

    monkeypatch.setattr(store_mod, "_atomic_write", crash_on_index)
    with pytest.raises(OSError, match="simulated crash"):
        s.save({"v": 2}, {"a": b"new"})
    monkeypatch.undo()
    assert Store(tmp_path).load() == ({"v": 1}, {"a": b"old"})

"""Durable snapshot of the server's state under ``--state DIR``.

Layout: ``DIR/state.json`` (the index: format version, JSON metadata, the names of the binary
blobs with their SHA-256, and a SHA-256 of all that) and ``DIR/blobs/<sha256>.bin`` (content-
addressed binary blobs, e.g. the encoded robot maps).

One server owns a state directory (:class:`StateLock`: an advisory lock on ``DIR/lock``, held
for the server's life and released on any exit, naming its holder). Temp files carry their
writer's process id; only the writer, or anyone once that process is gone, deletes them.

Writes are atomic and ordered: new blobs are written (temp file, fsync, rename; then one fsync of
the blob directory for all of them) before the index that names them replaces the old index
(temp file, fsync, rename, fsync of the directory), and only then are unreferenced blobs
deleted. A crash at any point leaves either the old or the new state, never a mix. Loading
verifies every checksum: a damaged or foreign state raises :class:`StateError` naming the file
and the problem — it is never silently loaded or discarded.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import socket
import tempfile
import time
from pathlib import Path

STATE_FORMAT = 1
MAX_INDEX_BYTES = 64 * 2**20


class StateError(ValueError):
    """The state directory cannot be loaded: the text says which file and why."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _canonical(obj: dict) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _atomic_write(path: Path, data: bytes, sync_dir: bool = True) -> None:
    """``data`` to ``path`` through a synced temp file and a rename; the rename itself synced
    (the directory) unless ``sync_dir`` is False: the caller syncs it once for several."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if sync_dir:
        _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _writer_gone(tmp: Path) -> bool:
    """A temp file ``.<name>.<pid>.<random>.tmp`` is this process's or its writer is gone."""
    parts = tmp.name.split(".")
    try:
        pid = int(parts[-3])
    except (IndexError, ValueError):
        return True  # not ours by its name: an older build's
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, someone else's
    return False


class StateLock:
    """The one owner of a state directory: an advisory lock (``flock``) on ``DIR/lock``, which
    the system releases on any exit of the holder, with the holder written in it. Taken: a
    :class:`StateError` naming the directory and the holder. A holder named in the file whose
    lock is gone (it was killed) is reported in ``stale``, and the lock taken over."""

    def __init__(self, directory: str | os.PathLike[str]):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / "lock"
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise StateError(
                f"{self.dir}: state directory in use by {holder} (one server per state directory; "
                "stop that one or give this one another --state)"
            ) from None
        self.stale = os.read(fd, 4096).decode(errors="replace").strip() or None
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {stamp}\n".encode(), 0)
        self._fd: int | None = fd

    def release(self) -> None:
        """Unlock (emptied first: a name left in the file means its holder died holding it)."""
        if self._fd is None:
            return
        os.ftruncate(self._fd, 0)
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> StateLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


class Store:
    """A state directory. ``save(meta, blobs)`` / ``load() -> (meta, blobs) | None``.

    Opening it verifies what it holds (``check``): a damaged state is reported at once, before a
    server connects anywhere or waits for its router, not when it is about to be used."""

    def __init__(self, directory: str | os.PathLike[str], check: bool = True):
        self.dir = Path(directory)
        self.index = self.dir / "state.json"
        self.blob_dir = self.dir / "blobs"
        if check:
            self.load()

    def save(self, meta: dict, blobs: dict[str, bytes]) -> None:
        """Persist ``meta`` (JSON-able, finite numbers) and the named binary ``blobs`` atomically."""
        self.blob_dir.mkdir(parents=True, exist_ok=True)
        names = {}
        written = False
        for name, data in blobs.items():
            digest = _sha256(data)
            path = self.blob_dir / f"{digest}.bin"
            if not path.exists():
                _atomic_write(path, data, sync_dir=False)
                written = True
            names[name] = digest
        if written:  # every new blob's rename durable before the index names it
            _fsync_dir(self.blob_dir)
        body = _canonical({"format": STATE_FORMAT, "meta": meta, "blobs": names})
        # the index is the body with its checksum added: "sha256" sorts last among the keys, so
        # the canonical document is the body's text with the checksum appended (encoded once)
        _atomic_write(self.index, body[:-1] + b',"sha256":"' + _sha256(body).encode() + b'"}')
        keep = {f"{d}.bin" for d in names.values()}
        for path in self.blob_dir.glob("*.bin"):
            if path.name not in keep:
                path.unlink(missing_ok=True)
        for path in [*self.blob_dir.glob(".*.tmp"), *self.dir.glob(f".{self.index.name}.*.tmp")]:
            if _writer_gone(path):  # left by a crash mid-write (not another live writer's)
                path.unlink(missing_ok=True)

    def load(self) -> tuple[dict, dict[str, bytes]] | None:
        """The saved state, ``None`` if the directory holds none; :class:`StateError` if damaged."""
        if not self.index.exists():
            return None
        raw = self.index.read_bytes()
        if len(raw) > MAX_INDEX_BYTES:
            raise StateError(f"{self.index}: {len(raw)} bytes, over {MAX_INDEX_BYTES}: not a state index")
        try:
            doc = json.loads(raw)
        except (ValueError, UnicodeDecodeError) as exc:
            raise StateError(f"{self.index}: not valid JSON ({exc}); the state is damaged") from None
        if not isinstance(doc, dict) or set(doc) != {"format", "meta", "blobs", "sha256"}:
            raise StateError(f"{self.index}: not a fleet-slam state index (keys {sorted(doc)[:8]!r:.100})")
        if doc["format"] != STATE_FORMAT:
            raise StateError(f"{self.index}: state format {doc['format']!r}, this build reads {STATE_FORMAT}")
        body = {k: doc[k] for k in ("format", "meta", "blobs")}
        if _sha256(_canonical(body)) != doc["sha256"]:
            raise StateError(f"{self.index}: checksum mismatch; the state is damaged")
        if not isinstance(doc["blobs"], dict) or not isinstance(doc["meta"], dict):
            raise StateError(f"{self.index}: meta and blobs must be objects")
        blobs = {}
        for name, digest in doc["blobs"].items():
            path = self.blob_dir / f"{digest}.bin"
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise StateError(f"{path}: blob {name!r} missing or unreadable ({exc.strerror})") from None
            if _sha256(data) != digest:
                raise StateError(f"{path}: blob {name!r} checksum mismatch; the state is damaged")
            blobs[name] = data
        return doc["meta"], blobs

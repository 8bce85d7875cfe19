"""Output folders that never lose a user's files: a render writes only into a folder that is empty or
holds an earlier render's files (listed in its manifest, `dataset_info.json` -> `files`), deletes
only those with --overwrite, and holds a lock (`.apose-render.lock`, flock'ed, its PID) while it writes.
What a render wrote is what it claimed in its journal (`claim`, before each write), never "whatever
is in the folder"."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import stat
import tempfile
import threading
from pathlib import Path

from apose_studio.assembly.fileio import atomic_write_text
from apose_studio.errors import AposeError
from apose_studio.safeio import read_json, read_text

MANIFEST = "dataset_info.json"  # its "files" lists every file a render wrote: all that --overwrite may delete
LOCK = ".apose-render.lock"
JOURNAL = ".apose-render.journal"  # each file a running render is about to write, one per line (survives kill -9)
OWN = (MANIFEST, LOCK, JOURNAL)
_ACTIVE: dict[Path, "OutputLock"] = {}  # output folders this process renders into now -> their lock
_ACTIVE_LOCK = threading.Lock()


def _files_under(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() or p.is_symlink())


def claim(path: str | Path) -> Path:
    """Note `path` as written by the render that holds its output folder (in the journal, before the
    write): only files claimed this way ever enter the manifest, so --overwrite never deletes a file
    someone else put there. A path outside any folder being rendered passes through."""
    path = Path(path)
    with _ACTIVE_LOCK:
        locks = list(_ACTIVE.items())
    for out, lock in locks:
        try:
            rel = path.resolve().relative_to(out).as_posix()
        except ValueError:
            continue
        lock.note(rel)
    return path


class OutputLock:
    """`out/.apose-render.lock`, held with `flock` while a render writes: a second render into the same
    folder stops with "in use by PID …" instead of interleaving its frames with the first one's. The
    kernel drops the lock when its process dies, so a stale lock file is simply locked again; there is
    no read-then-delete step that two starters could both win.

    While held it keeps the journal of the files the render writes (`claim`)."""

    def __init__(self, out: Path):
        self.out = Path(out)
        self.path = self.out / LOCK
        self.held = False
        self.fd: int | None = None
        self.files: set[str] = set()
        self._journal = None
        self._notes = threading.Lock()

    def __enter__(self) -> "OutputLock":
        for _ in range(50):
            try:  # never through a link: a planted `.apose-render.lock -> ~/notes.txt` must not be truncated
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o644)
            except OSError as e:
                if e.errno == errno.ELOOP:
                    raise AposeError(f"{self.path}: a symbolic link where the render's lock file goes; remove it, or "
                                     "choose another --out") from None
                raise AposeError(f"{self.out}: cannot write here ({e.strerror}); choose another --out") from None
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                os.close(fd)
                raise AposeError(f"{self.path}: not a regular file where the render's lock file goes; remove it, or "
                                 "choose another --out")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
                os.close(fd)
                who = f"PID {text}" if text.isdigit() else "another process"
                raise AposeError(f"{self.out}: in use by {who} (another apose render writes there); wait for it to "
                                 "finish, or choose another --out") from None
            try:  # the file locked must still be the one at the path (a finishing render unlinks its own)
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            self.fd, self.held = fd, True
            with _ACTIVE_LOCK:
                _ACTIVE[self.out.resolve()] = self
            return self
        raise AposeError(f"{self.path}: could not take the output folder's lock; try again")

    def note(self, rel: str) -> None:
        with self._notes:
            if rel in self.files or rel in OWN:
                return
            if self._journal is None:  # O_NOFOLLOW: a link planted as the journal is refused, never appended to
                fd = os.open(self.out / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
                self._journal = os.fdopen(fd, "a", encoding="utf-8")
            self._journal.write(rel + "\n")
            self._journal.flush()
            self.files.add(rel)

    def __exit__(self, *exc) -> None:
        if not self.held:
            return
        with _ACTIVE_LOCK:
            _ACTIVE.pop(self.out.resolve(), None)
        if self._journal is not None:
            self._journal.close()
            self._journal = None
        if exc[0] is None or (self.out / MANIFEST).is_file():  # the manifest now lists what the journal did
            (self.out / JOURNAL).unlink(missing_ok=True)
        self.path.unlink(missing_ok=True)  # while still locked: a waiting starter sees a new file, not this one
        os.close(self.fd)
        self.fd, self.held = None, False


def _journal_files(out: Path) -> list[str]:
    """The files a render that did not finish (kill -9, a full disk) had started to write."""
    p = Path(out) / JOURNAL
    if not p.is_file():
        return []
    try:
        return [line for line in read_text(p, "a render journal", 64 * 2**20).splitlines() if line and line not in OWN]
    except AposeError:
        return []


def _ours(out: Path) -> set[str]:
    """Files an apose render wrote here: listed in the manifest or a journal, and the temporary files of
    their atomic writes (`.NAME.xxxx.tmp` beside NAME) that a kill left behind."""
    return set(_manifest_files(out)) | set(_journal_files(out))


def _leftover_tmp(rel: str, ours: set[str]) -> bool:
    folder, _, name = rel.rpartition("/")
    if not (name.startswith(".") and name.endswith(".tmp")):
        return False
    stem = name[1:-4].rsplit(".", 1)[0]
    return (f"{folder}/{stem}" if folder else stem) in ours or stem in OWN


def make_output_dir(out: Path) -> Path:
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AposeError(f"{out}: exists and is not a folder; choose another --out")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise AposeError(f"{out}: cannot create this folder ({e.strerror}); choose another --out") from None
    return out


def check_output_dir(out: Path, overwrite: bool) -> None:
    """Refuse to mix a new render into an existing folder unless asked: nothing the user made is lost.
    With `overwrite`, the folder may hold only what an earlier render listed in its manifest."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AposeError(f"{out}: exists and is not a folder; choose another --out")
    present = [f for f in _files_under(out) if f != LOCK] if out.is_dir() else []
    if present and not overwrite:
        raise AposeError(f"{out}: folder is not empty; choose another --out, or pass --overwrite to "
                         "replace the dataset in it")
    if present:
        ours = _ours(out)
        foreign = [f for f in present if f not in ours and f not in OWN and not _leftover_tmp(f, ours)]
        if foreign:
            more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
            raise AposeError(f"{out}: holds files that no apose render wrote ({', '.join(foreign[:5])}{more}); "
                             "--overwrite replaces only a dataset's own files. Choose another --out, or move those away")
    check_writable(out)


def check_writable(out: Path) -> None:
    """A probe file written and removed: a read-only or full folder is refused before any work."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".apose-write-test.", dir=out)  # O_EXCL: never through a link
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise AposeError(f"{out}: cannot write here ({e.strerror}); choose another --out") from None


def _manifest_files(out: Path) -> list[str]:
    try:
        files = read_json(Path(out) / MANIFEST, "a dataset manifest").get("files", [])
    except (AposeError, AttributeError):
        return []
    return [f for f in files if isinstance(f, str)] if isinstance(files, list) else []


def write_manifest(out: Path, info: dict) -> None:
    """dataset_info.json listing the files this render wrote (claimed in its journal) that are on disk:
    a file someone else put into the folder meanwhile is never listed, so never deleted by --overwrite."""
    out = Path(out)
    lock = _ACTIVE.get(out.resolve())
    if lock is not None:
        with lock._notes:
            claimed = set(lock.files)
    else:
        claimed = set(_manifest_files(out))
    files = sorted(f for f in claimed if (out / f).is_file())
    atomic_write_text(out / MANIFEST, json.dumps({**info, "files": files}, indent=1))


def remove_previous_dataset(out: Path) -> None:
    """With --overwrite: remove only the files an earlier render listed or journaled (never other files)
    and its leftover temporary files, then the folders that this leaves empty."""
    out = Path(out)
    ours = _ours(out)
    for f in sorted(ours) + [f for f in _files_under(out) if _leftover_tmp(f, ours)]:
        p = (out / f)
        if p.resolve().is_relative_to(out.resolve()) and (p.is_file() or p.is_symlink()):
            p.unlink()
    (out / MANIFEST).unlink(missing_ok=True)
    (out / JOURNAL).unlink(missing_ok=True)
    for d in sorted((p for p in out.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()

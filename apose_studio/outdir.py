"""Output folders that never lose a user's files: a render writes only into a folder that is empty or
holds an earlier render's files (listed in its manifest, `dataset_info.json` -> `files`), deletes
only those with --overwrite, and holds a lock (`.apose-render.lock`, its PID) while it writes."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .errors import AposeError
from .fileio import atomic_write_text

MANIFEST = "dataset_info.json"  # its "files" lists every file a render wrote: all that --overwrite may delete
LOCK = ".apose-render.lock"


def _files_under(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() or p.is_symlink())


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class OutputLock:
    """`out/.apose-render.lock` holding the writer's PID: a second render into the same folder stops with
    "in use by PID …" instead of interleaving its frames with the first one's. A lock whose process is
    gone is taken over."""

    def __init__(self, out: Path):
        self.path = Path(out) / LOCK
        self.held = False

    def __enter__(self) -> "OutputLock":
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or "0")
                except (OSError, ValueError):
                    pid = 0
                if pid and _pid_alive(pid):
                    raise AposeError(f"{self.path.parent}: in use by PID {pid} (another apose render writes there); "
                                     "wait for it to finish, or choose another --out") from None
                self.path.unlink(missing_ok=True)  # stale: its process is gone
                continue
            with os.fdopen(fd, "w") as f:
                f.write(str(os.getpid()))
            self.held = True
            return self
        raise AposeError(f"{self.path}: could not take the output folder's lock; remove the file if no render runs")

    def __exit__(self, *exc) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False


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
        listed = set(_manifest_files(out))
        foreign = [f for f in present if f not in listed and f != MANIFEST]
        if foreign:
            more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
            raise AposeError(f"{out}: holds files that no apose render wrote ({', '.join(foreign[:5])}{more}); "
                             "--overwrite replaces only a dataset's own files. Choose another --out, or move those away")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".apose-write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise AposeError(f"{out}: cannot write here ({e.strerror}); choose another --out") from None


def _manifest_files(out: Path) -> list[str]:
    try:
        files = json.loads((Path(out) / MANIFEST).read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [f for f in files if isinstance(f, str)]


def write_manifest(out: Path, info: dict) -> None:
    """dataset_info.json with the list of every file under `out` (the render refused a folder holding
    anything else, so all of them are its own)."""
    files = [f for f in _files_under(Path(out)) if f not in (MANIFEST, LOCK)]
    atomic_write_text(Path(out) / MANIFEST, json.dumps({**info, "files": files}, indent=1))


def remove_previous_dataset(out: Path) -> None:
    """With --overwrite: remove only the files an earlier render listed (never other files), then the
    folders that this leaves empty."""
    out = Path(out)
    for f in _manifest_files(out):
        p = (out / f)
        if p.resolve().is_relative_to(out.resolve()) and (p.is_file() or p.is_symlink()):
            p.unlink()
    (out / MANIFEST).unlink(missing_ok=True)
    for d in sorted((p for p in out.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()

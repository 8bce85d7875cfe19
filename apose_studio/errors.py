"""The project's own exception types. The CLI and studio turn them into one readable line each."""

from __future__ import annotations

import errno
from dataclasses import dataclass

from apose_studio.text import escaped


def os_error_text(e: OSError) -> str:
    """One line for an OSError (a full disk, a read-only folder, a name too long): the file, what the
    system said, and what to do. The CLI and the studio show it instead of a traceback."""
    where = f"{escaped(str(e.filename))}: " if getattr(e, "filename", None) else ""
    fix = {errno.ENOSPC: "free some disk space or choose another folder (nothing half-written was kept)",
           errno.EDQUOT: "free some space under your quota or choose another folder",
           errno.EROFS: "the file system is read-only; choose another folder",
           errno.EACCES: "permission denied; choose a folder you may write to",
           errno.EPERM: "not permitted; choose a folder you may write to",
           errno.ENAMETOOLONG: "use a shorter path",
           errno.EMFILE: "too many open files; raise `ulimit -n`"}.get(e.errno, "check the path and try again")
    return f"{where}{e.strerror or e}; {fix}"


class AposeError(Exception):
    """Base class: a problem the user can fix, with a message that says what and how."""


@dataclass(frozen=True)
class Problem:
    """One validation problem: `where` is a file and 0-based key path, `what` says what was expected."""

    file: str
    key: str
    what: str

    def __str__(self) -> str:
        return f"{self.file}: {escaped(self.key)}: {self.what}" if self.key else f"{self.file}: {self.what}"


class AssemblyError(AposeError):
    """An assembly file that cannot be used; carries every problem found, one per line."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        super().__init__("\n".join(str(p) for p in self.problems))


class MeshError(AposeError):
    """A CAD file that is missing, corrupt, empty or not a surface mesh."""


class DatasetError(AposeError):
    """A dataset folder or frame that is missing pieces or cannot be read."""


class RenderError(AposeError):
    """Bad render settings (unknown step, empty range, unwritable output)."""

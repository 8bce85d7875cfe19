"""The project's own exception types. The CLI and studio turn them into one readable line each."""

from __future__ import annotations

from dataclasses import dataclass

from apose_studio.text import escaped


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

"""Writing files so that nothing the user made is lost: atomic replacement that keeps the file's mode
(new files get the usual mode from the umask), an optional `NAME.bak` of the previous version, and a
round-trip YAML update that keeps a hand-written file's comments and key order.

Also the strict YAML reader (no aliases, no duplicate keys, bounded nesting) the assembly loader uses.
"""

from __future__ import annotations

import io
import os
import re
import secrets
import shutil
import stat
import tempfile
import threading
import time
from pathlib import Path

import yaml
from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq

from apose_studio.errors import AposeError, AssemblyError, Problem

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process umask (read from /proc where it can be, so no thread ever sees it changed)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def atomic_write_bytes(path: str | Path, data: bytes, backup: bool = False) -> None:
    """Write beside the target, flush to disk, then rename over it: a reader never sees half a file.

    The result has the mode the replaced file had, or 0666 less the umask for a new file (a bare
    temporary file would leave 0600 behind). With `backup`, the previous version is kept as NAME.bak,
    itself replaced atomically."""
    path = Path(path)
    mode = stat.S_IMODE(path.stat().st_mode) if path.is_file() else 0o666 & ~current_umask()
    if backup and path.is_file():
        keep_backup(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _sweep_stale_tmp(path)


BACKUP_COPY_BYTES = 64 * 2 ** 20  # where a file system has no hard links, a backup is copied up to this size


def keep_backup(path: Path) -> None:
    """Keep the file at `path` as NAME.bak (replaced atomically) before it is replaced. The old file
    itself becomes the backup through a hard link: nothing is read or copied, whatever its size (a
    2 GB file a user saves over costs no memory and no disk). A file system without hard links gets a
    streamed copy up to BACKUP_COPY_BYTES; a larger file is refused rather than lost."""
    bak = path.with_name(path.name + ".bak")
    if bak.is_dir() and not bak.is_symlink():
        raise AposeError(f"{bak}: a folder where the previous version of {path.name} is kept; move it away (or save "
                         "under another name)")
    tmp = path.with_name(f".{bak.name}.{secrets.token_hex(6)}.tmp")  # swept like the writer's own when left
    try:
        os.link(path, tmp)
    except OSError:
        size = path.stat().st_size
        if size > BACKUP_COPY_BYTES:
            raise AposeError(f"{path}: {size / 2 ** 20:.0f} MB, and this file system cannot keep it as {bak.name} "
                             f"without a copy (at most {BACKUP_COPY_BYTES // 2 ** 20} MB); move it away or save "
                             "under another name") from None
        shutil.copyfile(path, tmp)  # in chunks: bounded memory
    try:
        os.replace(tmp, bak)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise AposeError(f"{bak}: the previous version cannot be kept there ({e.strerror}); move it away or save "
                         "under another name") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


STALE_TMP_SECONDS = 600  # a temporary file of ours this old was left by a killed writer, not one in flight


def _sweep_stale_tmp(path: Path) -> None:
    """Remove `.NAME.*.tmp` (and `.NAME.bak.*.tmp`) files beside `path` that a writer killed mid-save
    left behind; only ours (that exact prefix) and only old ones, so a save in flight is never touched."""
    now, prefix = time.time(), f".{path.name}."  # also matches .NAME.bak.*.tmp
    try:
        names = [n for n in os.listdir(path.parent) if n.startswith(prefix) and n.endswith(".tmp")]
    except OSError:
        return
    for n in names:
        p = path.parent / n
        try:
            if p.is_file() and not p.is_symlink() and now - p.stat().st_mtime > STALE_TMP_SECONDS:
                p.unlink()
        except OSError:
            pass


def atomic_write_text(path: str | Path, text: str, backup: bool = False) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), backup=backup)


def describe_path(path: str | Path, wanted: str) -> str:
    """Why `path` is not the regular file that was wanted, in words ("a folder", "a device")."""
    p = Path(path)
    if not p.exists():
        return f"file not found; type the path of {wanted}" if not p.is_symlink() else "a broken link"
    if p.is_dir():
        return f"a folder, not a file; choose {wanted} inside it"
    if not p.is_file():
        return f"not a regular file (a device, pipe or socket); choose {wanted}"
    return "a file"


# ----------------------------------------------------------------------------- YAML


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML without aliases (a few lines of anchors can expand to gigabytes) and without duplicate keys
    (two parts with one id would silently become one)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, "aliases (*name) are not allowed in assembly files; write the value out", event.start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r} (first at line {seen[key] + 1}); each key may appear once",
                        key_node.start_mark)
                seen[key] = key_node.start_mark.line
            except TypeError:  # an unhashable key: the base class reports it
                pass
        return super().construct_mapping(node, deep)

    def construct_yaml_int(self, node):
        """An integer; one of more digits than Python converts (4300) is named at its line, not a ValueError."""
        try:
            return super().construct_yaml_int(node)
        except ValueError:
            raise yaml.constructor.ConstructorError(
                None, None, f"a whole number of {len(str(node.value))} digits: far too long to be a value of this file",
                node.start_mark) from None


_StrictLoader.add_constructor("tag:yaml.org,2002:map", _StrictLoader.construct_yaml_map)
_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)
# YAML 1.1 (PyYAML) reads 1e308 and 2E-3 (no dot) as text; YAML 1.2 and every user read them as numbers
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789"))


def yaml_number(x: float) -> float | int:
    """A number as a saved file writes it: round-off noise away (1e-12 of a unit), whole numbers as ints."""
    r = round(float(x), 12)
    return int(r) if r == int(r) and abs(r) < 1e15 else r


def parse_yaml(text: str, file: str):
    """YAML text to plain data, with errors naming the line; no aliases, no duplicate keys, bounded nesting."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(e, "problem", None) or "not valid YAML"
        kind = "YAML error" if isinstance(e, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise AssemblyError([Problem(file, "", f"{where}{kind}: {problem}")]) from None
    except RecursionError:
        raise AssemblyError([Problem(file, "", "nested far too deeply to be an assembly file")]) from None


def _same(a, b) -> bool:
    """Equal as data (1 == 1.0; a ruamel CommentedMap equals a dict with the same items)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b or (type(a) is type(b) and a == b)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    return a == b


def _flow(value):
    """New short lists of scalars in flow style ([x, y, z]), as the format doc writes them."""
    if isinstance(value, dict):
        out = CommentedMap()
        for k, v in value.items():
            out[k] = _flow(v)
        return out
    if isinstance(value, (list, tuple)):
        out = CommentedSeq(_flow(v) for v in value)
        if all(not isinstance(v, (list, tuple, dict)) for v in value) and len(value) <= 16:
            out.fa.set_flow_style()
        return out
    return value


def merge_into(old, new, keep=None):
    """`new` written into the round-trip tree `old`: keys and items whose value did not change keep
    their node (and so their comments and style), keys keep their order, new keys go last, removed
    keys go. `keep(path, old_value, new_value) -> bool` may declare two differently written values
    the same (a rotation written as Euler angles that the new data writes as a quaternion)."""
    return _merge(old, new, (), keep)


def _merge(old, new, path: tuple, keep):
    if keep is not None and keep(path, old, new):
        return old
    if isinstance(old, dict) and isinstance(new, dict):
        for k in [k for k in old if k not in new]:
            del old[k]
        for k, v in new.items():
            old[k] = _merge(old[k], v, path + (k,), keep) if k in old else _flow(v)
        return old
    if isinstance(old, list) and isinstance(new, (list, tuple)) and not _same(old, new):
        if all(isinstance(v, dict) for v in list(old) + list(new)):  # e.g. steps: item by item
            del old[len(new):]
            for i, v in enumerate(new):
                if i < len(old):
                    old[i] = _merge(old[i], v, path + (i,), keep)
                else:
                    old.append(_flow(v))
            return old
        return _flow(new)
    return old if _same(old, new) else _flow(new)


def roundtrip_yaml(previous_text: str | None, data: dict, keep=None) -> str:
    """YAML text of `data`; where `previous_text` is a YAML mapping, written into it so that what the
    user wrote by hand (comments, key order, quoting) stays wherever the data did not change."""
    yaml = YAML(typ="rt")
    yaml.width = 4096
    yaml.indent(mapping=2, sequence=4, offset=2)
    tree = None
    if previous_text:
        try:
            tree = yaml.load(previous_text)
        except Exception:  # unreadable as YAML: write afresh
            tree = None
    tree = merge_into(tree, data, keep) if isinstance(tree, dict) else _flow(data)
    buf = io.StringIO()
    yaml.dump(tree, buf)
    return buf.getvalue()

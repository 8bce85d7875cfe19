"""Output folders (outdir.py): the lock is atomic under many concurrent starters, and --overwrite deletes
only what a render wrote, also after a render was killed (its journal)."""

import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time

import pytest

from apose_studio.data.outdir import (
    JOURNAL,
    LOCK,
    MANIFEST,
    OutputLock,
    check_output_dir,
    claim,
    remove_previous_dataset,
    write_manifest,
)
from apose_studio.errors import AposeError

from ..conftest import REPO, SAMPLES


def _starter(out, barrier, log):
    barrier.wait()
    try:
        with OutputLock(out):
            t0 = time.monotonic()
            time.sleep(0.05)
            log.put(("held", t0, time.monotonic()))
    except AposeError as e:
        log.put(("refused", str(e), 0.0))


def test_many_starters_on_a_stale_lock_never_hold_it_together(tmp_path):
    """A stale lock file (its writer died) and 16 processes started at once, ten times over: at no moment
    do two of them hold the folder (the old read-then-unlink takeover let two win in 21 of 200 trials)."""
    ctx = mp.get_context("fork")
    overlaps, held_total = 0, 0
    for trial in range(10):
        out = tmp_path / f"t{trial}"
        out.mkdir()
        (out / LOCK).write_text("999999999")  # left by a process that is gone
        barrier, log = ctx.Barrier(16), ctx.Queue()
        procs = [ctx.Process(target=_starter, args=(out, barrier, log)) for _ in range(16)]
        for p in procs:
            p.start()
        results = [log.get(timeout=60) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        spans = sorted((a, b) for kind, a, b in results if kind == "held")
        held_total += len(spans)
        overlaps += sum(1 for (a0, a1), (b0, b1) in zip(spans, spans[1:]) if b0 < a1)
        assert all("in use by" in a for kind, a, _ in results if kind == "refused")
    assert held_total >= 10  # each trial someone got it
    assert overlaps == 0


def test_read_only_output_folder_is_refused_before_the_lock(tmp_path):
    if os.geteuid() == 0:
        out = tmp_path / "ro"
        out.mkdir()
        subprocess.run(["chattr", "+i", str(out)], check=False, capture_output=True)
        immutable = subprocess.run(["lsattr", "-d", str(out)], capture_output=True, text=True).stdout.split()[:1]
        if not immutable or "i" not in immutable[0]:
            pytest.skip("running as root without chattr: a read-only folder cannot be made")
    else:
        out = tmp_path / "ro"
        out.mkdir()
        out.chmod(0o500)
    try:
        with pytest.raises(AposeError, match="cannot write here"):
            with OutputLock(out):
                pass
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=False, capture_output=True)
        out.chmod(0o700)


def test_a_file_put_in_during_a_render_is_never_listed_nor_deleted(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    with OutputLock(out):
        (claim(out / "test" / "000001" / "a.png")).parent.mkdir(parents=True)
        (out / "test" / "000001" / "a.png").write_bytes(b"ours")
        (out / "test" / "000001" / "mine.txt").write_text("the user's, put here meanwhile")
        (out / "notes.md").write_text("the user's too")
        write_manifest(out, {"format": "x"})
    files = json.loads((out / MANIFEST).read_text())["files"]
    assert files == ["test/000001/a.png"]
    assert not (out / JOURNAL).exists() and not (out / LOCK).exists()
    with pytest.raises(AposeError, match="no apose render wrote .*mine.txt"):
        check_output_dir(out, overwrite=True)
    (out / "test" / "000001" / "mine.txt").unlink()
    (out / "notes.md").unlink()
    check_output_dir(out, overwrite=True)
    remove_previous_dataset(out)
    assert list(out.iterdir()) == []


def test_overwrite_after_kill_9_recovers_the_render_s_own_files(tmp_path):
    """A render killed with SIGKILL mid-way leaves frames, a journal and perhaps a temporary file: the next
    --overwrite recognises all of them as apose's (it refused them before) and replaces the dataset."""
    out = tmp_path / "ds"
    asm = SAMPLES / "planetary_reducer" / "assembly.yaml"
    cmd = [sys.executable, "-m", "apose_studio.cli.commands", "render", str(asm), "--out", str(out), "--frames", "400",
           "--steps", "1"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t0 = time.time()
        while time.time() - t0 < 120 and len(list(out.glob("test/000001/depth/*.png"))) < 3:
            time.sleep(0.05)
        assert len(list(out.glob("test/000001/depth/*.png"))) >= 3, "the render did not start"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert (out / JOURNAL).is_file()
    (out / "models" / ".models_info.json.abc123.tmp").write_text("{}")  # what a kill during an atomic write leaves
    check_output_dir(out, overwrite=True)  # apose's files, every one of them
    (out / "mine.txt").write_text("precious")
    with pytest.raises(AposeError, match="mine.txt"):
        check_output_dir(out, overwrite=True)
    (out / "mine.txt").unlink()
    done = subprocess.run(cmd[:-4] + ["--frames", "1", "--steps", "1", "--overwrite"], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    files = json.loads((out / MANIFEST).read_text())["files"]
    assert not (out / JOURNAL).exists()
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == sorted(files + [MANIFEST])


def test_a_held_lock_names_the_pid_and_a_finished_one_leaves_nothing(tmp_path):
    """While held, the lock file holds the PID that the refusal names; after a clean exit neither the lock
    nor the journal is left (a kill leaves the journal: test_overwrite_after_kill_9...); a lock that ended
    by an error keeps the journal unless a manifest lists the files."""
    out = tmp_path / "ds"
    out.mkdir()
    with OutputLock(out) as lock:
        assert lock.held and (out / LOCK).read_text() == str(os.getpid())
        claim(out / "a.png")
        (out / "a.png").write_bytes(b"x")
        with pytest.raises(AposeError, match=rf"in use by PID {os.getpid()} \(another apose render"):
            with OutputLock(out):
                pass
        assert (out / JOURNAL).read_text() == "a.png\n"
    assert not lock.held and lock.fd is None
    assert not (out / LOCK).exists() and not (out / JOURNAL).exists()
    (out / LOCK).write_text("not a pid")  # a stale lock file of another kind: taken over, its text replaced
    with pytest.raises(RuntimeError):
        with OutputLock(out):
            claim(out / "b.png")
            raise RuntimeError("a render that failed")
    assert (out / JOURNAL).read_text() == "b.png\n" and not (out / LOCK).exists()


def test_the_refusal_lists_five_foreign_files_and_counts_the_rest(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    for k in range(7):
        (out / f"note{k}.txt").write_text("mine")
    with pytest.raises(AposeError) as e:
        check_output_dir(out, overwrite=True)
    text = str(e.value)
    assert "note0.txt, note1.txt, note2.txt, note3.txt, note4.txt and 2 more)" in text and "note5" not in text
    for k in range(2, 7):
        (out / f"note{k}.txt").unlink()
    with pytest.raises(AposeError) as e:
        check_output_dir(out, overwrite=True)
    assert "(note0.txt, note1.txt);" in str(e.value)  # two: no "more"
    with pytest.raises(AposeError, match="folder is not empty; choose another --out, or pass --overwrite"):
        check_output_dir(out, overwrite=False)


def test_only_the_render_s_own_temporary_files_count_as_its_leftovers(tmp_path):
    """`.NAME.xxxx.tmp` beside a file the manifest lists is a kill's leftover (removed by --overwrite);
    `NAME.tmp`, `.other.xxxx.tmp` (no such file listed) and `.NAME.tmp.bak` are someone else's."""
    out = tmp_path / "ds"
    (out / "rgb").mkdir(parents=True)
    (out / "rgb" / "000000.png").write_bytes(b"x")
    (out / MANIFEST).write_text(json.dumps({"files": ["rgb/000000.png"]}))
    (out / "rgb" / ".000000.png.k3j2.tmp").write_bytes(b"half")
    (out / f".{MANIFEST}.q9.tmp").write_text("half")
    check_output_dir(out, overwrite=True)  # only ours: accepted
    for foreign in ("rgb/000000.png.tmp", "rgb/.other.png.k3j2.tmp", "rgb/.000000.png.k3j2.tmp.bak"):
        (out / foreign).write_bytes(b"someone's")
        with pytest.raises(AposeError, match="holds files that no apose render wrote"):
            check_output_dir(out, overwrite=True)
        (out / foreign).unlink()
    remove_previous_dataset(out)
    assert not out.exists() or not any(out.rglob("*"))


def test_the_manifest_lists_what_was_claimed_and_is_on_disk(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    with OutputLock(out):
        for name in ("a.png", "b.png"):
            claim(out / name)
        (out / "a.png").write_bytes(b"x")  # b.png was claimed, never written
        (out / "c.png").write_bytes(b"y")  # put there by someone else meanwhile
        write_manifest(out, {"format": "test"})
    doc = json.loads((out / MANIFEST).read_text())
    assert doc == {"format": "test", "files": ["a.png"]}
    assert (out / MANIFEST).read_text().startswith('{\n "format"')  # indented one space, as readers diff it


def test_a_lock_without_claims_and_claims_made_twice(tmp_path):
    """A render that wrote nothing leaves neither lock nor journal; a file claimed twice is journaled once,
    and the folder's own files (the manifest) are never journaled, so the manifest never lists itself."""
    out = tmp_path / "ds"
    out.mkdir()
    with OutputLock(out):
        pass
    assert sorted(p.name for p in out.iterdir()) == []
    with OutputLock(out):
        for _ in range(2):
            claim(out / "a.png")
        claim(out / MANIFEST)
        (out / "a.png").write_bytes(b"x")
        write_manifest(out, {})
        assert (out / JOURNAL).read_text() == "a.png\n"
    assert json.loads((out / MANIFEST).read_text())["files"] == ["a.png"]


def test_overwrite_never_deletes_outside_the_folder(tmp_path):
    """A manifest that lists a path leading out of the folder (hand-edited, or planted) deletes nothing there."""
    out = tmp_path / "ds"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's")
    (out / "a.png").write_bytes(b"x")
    (out / MANIFEST).write_text(json.dumps({"files": ["a.png", "../victim.txt", str(victim)]}))
    remove_previous_dataset(out)
    assert victim.read_text() == "the user's" and not (out / "a.png").exists()


@pytest.mark.parametrize("n,tail", [(5, ")"), (6, " and 1 more)")])
def test_the_refusal_counts_past_five(tmp_path, n, tail):
    out = tmp_path / "ds"
    out.mkdir()
    for k in range(n):
        (out / f"note{k}.txt").write_text("mine")
    with pytest.raises(AposeError) as e:
        check_output_dir(out, overwrite=True)
    assert f"note4.txt{tail};" in str(e.value) and "note5" not in str(e.value)

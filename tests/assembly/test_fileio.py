"""Saves that lose nothing: file modes, backups, and round-trip YAML that keeps a user's comments."""

import os
import stat

import numpy as np

from apose_studio.assembly.fileio import atomic_write_text, current_umask, describe_path, roundtrip_yaml
from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.studio import authoring


def mode(p) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def test_atomic_write_keeps_the_mode_and_new_files_follow_the_umask(tmp_path):
    p = tmp_path / "a.txt"
    atomic_write_text(p, "one")
    assert mode(p) == 0o666 & ~current_umask() and p.read_text() == "one"  # not mkstemp's 0600
    os.chmod(p, 0o640)
    atomic_write_text(p, "two", backup=True)
    assert mode(p) == 0o640 and p.read_text() == "two"
    assert (tmp_path / "a.txt.bak").read_text() == "one"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.txt", "a.txt.bak"]  # no temporary file left


def test_rendered_json_files_are_not_private(tmp_path):
    from apose_studio.data.dataset import write_json

    write_json(tmp_path / "scene_gt.json", {"0": []})
    assert mode(tmp_path / "scene_gt.json") == 0o666 & ~current_umask()


def test_resaving_a_hand_written_file_keeps_comments_order_and_style(tiny_dir):
    path = tiny_dir / "assembly.yaml"
    text = "# rig for line 3 -- ask Ana before changing\n" + path.read_text().replace(
        "  peg:\n", "  peg:  # the dowel\n").replace("format: apose-assembly/1\n", "format: apose-assembly/1\n# units below\n")
    path.write_text(text)
    asm = load_assembly(path)
    T = asm.steps[1].T_base_part.copy()
    T[0, 3] = 0.0025
    save_assembly(authoring.edit_step(asm, 1, T_base_part=T), path)
    out = path.read_text()
    for kept in ("# rig for line 3 -- ask Ana before changing\n", "# units below\n", "peg:  # the dowel\n",
                 "rotation: {euler_deg: [0, 0, 90], order: xyz}"):  # step 1 unchanged: written as the user wrote it
        assert kept in out, kept
    assert "translation: [2.5, 10, 0]" in out  # the edit, in the file's unit
    assert out.index("plate:") < out.index("peg:") < out.index("cap:")
    back = load_assembly(path)
    np.testing.assert_allclose(back.steps[1].T_base_part, T, atol=1e-12)
    np.testing.assert_allclose(back.steps[0].T_base_part, asm.steps[0].T_base_part, atol=1e-12)


def test_roundtrip_of_unreadable_previous_text_writes_afresh():
    out = roundtrip_yaml("key: [unclosed\n", {"a": [1, 2, 3], "b": {"c": 1}})
    assert out == "a: [1, 2, 3]\nb:\n  c: 1\n"


def test_describe_path_says_what_is_there(tmp_path):
    assert "file not found" in describe_path(tmp_path / "nope.yaml", "x")
    assert "a folder, not a file" in describe_path(tmp_path, "x")
    assert "not a regular file" in describe_path("/dev/null", "x")

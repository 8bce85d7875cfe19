"""Grasps and the gripper in the assembly file (ASSEMBLY_FORMAT.md, "Optional part keys: grasps, and the
gripper"): loaded in metres with the file's units, saved and read back equal, and every mistake named by
its key path."""

import numpy as np
import pytest

from apose_studio.assembly.model import load_assembly, save_assembly
from apose_studio.errors import AssemblyError

GRASPS = """\
    grasps:
      - name: side
        pose_in_part:
          translation: [0, 0, 8]
          rotation: {euler_deg: [90, 0, 0], order: xyz}
        width: 8
      - name: top
        pose_in_part: {translation: [0, 0, 10], rotation: {quat_wxyz: [0, 1, 0, 0]}}
gripper:
  type: parallel
  max_width: 85
  finger_length: 40
"""


def with_grasps(tiny_dir, grasps: str = GRASPS):
    text = (tiny_dir / "assembly.yaml").read_text()
    text = text.replace("    symmetry: {axis: [0, 0, 1], order: 0}\n", "    symmetry: {axis: [0, 0, 1], order: 0}\n" + grasps
                        .split("gripper:")[0])
    if "gripper:" in grasps:
        text = text.replace("steps:\n", "gripper:" + grasps.split("gripper:")[1] + "steps:\n")
    (tiny_dir / "assembly.yaml").write_text(text)
    return tiny_dir / "assembly.yaml"


def test_grasps_load_in_metres_and_round_trip(tiny_dir, tmp_path):
    asm = load_assembly(with_grasps(tiny_dir))
    side, top = asm.parts["peg"].grasps
    assert side.name == "side" and side.width == pytest.approx(0.008)
    np.testing.assert_allclose(side.T_part_gripper[:3, 3], (0, 0, 0.008), atol=1e-15)
    np.testing.assert_allclose(side.T_part_gripper[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(top.T_part_gripper[:3, :3], np.diag([1, -1, -1]), atol=1e-12)
    assert top.width is None
    assert asm.gripper.max_width == pytest.approx(0.085) and asm.gripper.finger_length == pytest.approx(0.040)
    saved = save_assembly(asm, tiny_dir / "again.yaml")
    assert load_assembly(saved) == asm
    save_assembly(asm, tiny_dir / "assembly.yaml")  # re-saved in place: the user's Euler angles stay as written
    assert "euler_deg: [90, 0, 0]" in (tiny_dir / "assembly.yaml").read_text()


@pytest.mark.parametrize("grasps, key, words", [
    (GRASPS.replace("name: top", "name: side"), "parts.peg.grasps[1].name", "unique"),
    (GRASPS.replace("        width: 8\n", "        width: 90\n"), "parts.peg.grasps[0].width", "more than the gripper opens"),
    (GRASPS.replace("        width: 8\n", "        width: -1\n"), "parts.peg.grasps[0].width", "above 0"),
    (GRASPS.replace("[0, 1, 0, 0]", "[0, 0, 0, 0]"), "parts.peg.grasps[1].pose_in_part.rotation.quat_wxyz", "non-zero"),
    (GRASPS.replace("{euler_deg: [90, 0, 0], order: xyz}", "{matrix: [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}"),
     "parts.peg.grasps[0].pose_in_part.rotation.matrix", "rotation matrix"),
    (GRASPS.replace("type: parallel", "type: mesh"), "gripper.mesh", "needs the path"),
    (GRASPS.replace("type: parallel", "type: suction"), "gripper.type", "parallel, mesh"),
    (GRASPS.replace("        width: 8\n", "        width: 8\n        force: 3\n"), "parts.peg.grasps[0].force", "unknown key"),
    (GRASPS.replace("translation: [0, 0, 8]", "translation: [0, 0]"), "parts.peg.grasps[0].pose_in_part.translation",
     "3 numbers"),
])
def test_grasp_mistakes_name_their_key(tiny_dir, grasps, key, words):
    with pytest.raises(AssemblyError) as e:
        load_assembly(with_grasps(tiny_dir, grasps))
    problems = [p for p in e.value.problems if p.key == key]
    assert problems and words in problems[0].what, str(e.value)


def test_a_file_without_grasps_is_unchanged(tiny_dir):
    asm = load_assembly(tiny_dir / "assembly.yaml")
    assert asm.gripper is None and all(p.grasps == () for p in asm.parts.values())
    save_assembly(asm, tiny_dir / "s.yaml")
    text = (tiny_dir / "s.yaml").read_text()
    assert "grasps" not in text and "gripper" not in text

"""The Mates and Approach folders without a browser (tests/e2e picks faces with the mouse): the
approach arrow, mate edits through the panel, undo over them, STEP files with several solids."""

import numpy as np

from ..conftest import SAMPLES
from .conftest import act, errors


def test_approach_arrow_follows_the_step_and_undo(studio):
    st = studio(SAMPLES / "planetary_reducer" / "assembly.yaml")
    st.steps.step_index = 0
    st.refresh_assembly_widgets()
    assert "/assembly/approach" in st.nodes  # the sample's sun gear comes down 30 mm
    seg = st.nodes["/assembly/approach"]._impl.props.points
    np.testing.assert_allclose(seg[0, 0] - seg[0, 1], [0, 0, 0.03], atol=1e-6)  # starts 30 mm above, points down
    st.mates.f_app_dir.value = "none"
    act(st, st.mates.on_set_approach)
    assert st.asm.steps[0].approach is None and "/assembly/approach" not in st.nodes
    st.mates.f_app_dir.value, st.mates.f_app_len.value = "along the mate axis", 45.0
    act(st, st.mates.on_set_approach)
    np.testing.assert_allclose(st.asm.steps[0].approach.direction, [0, 0, -1])  # down the shaft, towards the motor
    assert abs(st.asm.steps[0].approach.distance - 0.045) < 1e-12
    act(st, lambda c: st.undo_redo("Undo", c))
    assert st.asm.steps[0].approach is None
    act(st, lambda c: st.undo_redo("Undo", c))
    assert abs(st.asm.steps[0].approach.distance - 0.03) < 1e-12
    assert errors(st) == []


def test_mate_list_edits_and_refusals(studio):
    st = studio(SAMPLES / "planetary_reducer" / "assembly.yaml")
    st.steps.step_index = 0
    st.refresh_assembly_widgets()
    assert "the pose is fixed" in st.mates.list_html.content and "gap 3.00 mm" in st.mates.list_html.content
    st.mates.f_mate.value = "2. contact"
    st.mates.f_value.value = 5.0
    act(st, st.mates.on_set_value)
    assert abs(st.asm.steps[0].T_base_part[2, 3] - 0.054) < 1e-12  # the hub 5 mm above the boss
    act(st, lambda c: st.mates.on_mate_action("Flip", c))  # a contact does not flip
    assert "only a coaxial mate flips" in errors(st)[-1][1]
    act(st, lambda c: st.mates.on_mate_action("Delete", c))
    assert [m.type for m in st.asm.steps[0].mates] == ["coaxial", "contact"]
    assert "sliding along" in st.mates.list_html.content  # nothing holds the height now
    act(st, lambda c: st.mates.on_plane_mate("Contact", c))
    assert "pick a flat face of the part and one of its base first" in errors(st)[-1][1]


def test_a_step_file_adds_a_part_per_solid(studio, tmp_path):
    st = studio(root=SAMPLES)
    st.files.f_mesh.value = str(SAMPLES / "step_bracket" / "bracket.step")
    act(st, lambda c: st.files.on_add_parts(c))
    assert sorted(st.asm.parts) == ["bushing", "pin", "plate"] and errors(st) == []
    assert {p.solid for p in st.asm.parts.values()} == {"plate", "pin", "bushing"}

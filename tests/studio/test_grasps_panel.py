"""The Grasps folder without a browser: a grasp made from a picked face of the step's part, drawn as a
gripper at the place and the pre-place, listed, undone, deleted and saved with the assembly."""

import shutil

import numpy as np

from ..conftest import SAMPLES
from .conftest import act, errors


def test_a_grasp_from_a_picked_face_is_drawn_saved_and_undone(studio, tmp_path):
    from apose_studio.assembly.model import load_assembly

    shutil.copytree(SAMPLES / "planetary_reducer", tmp_path / "pr")
    st = studio(tmp_path / "pr" / "assembly.yaml", root=tmp_path)
    st.steps.step_index = 2  # the carrier (grasp "shaft" in the sample), with a 30 mm approach
    st.refresh_assembly_widgets()
    assert st.grasps.f_grasp.options == ("shaft",)
    assert {"/assembly/gripper/place", "/assembly/gripper/preplace"} <= set(st.nodes)
    place = st.nodes["/assembly/gripper/place"]
    T_world_carrier = st.state.T_world_shown("carrier")
    np.testing.assert_allclose(place.position, (T_world_carrier @ st.asm.parts["carrier"].grasps[0].T_part_gripper)[:3, 3],
                               atol=1e-6)
    # no pick yet: said, nothing added
    act(st, st.grasps.on_add)
    assert "pick a face of carrier first" in errors(st)[-1][1]
    # a click on the side of the carrier's output shaft (in the carrier's frame): its round face, 8 mm across
    feature = st.mates.picker("carrier").pick(np.array([0.05, 0.0, 0.012]), np.array([-1.0, 0.0, 0.0]))
    assert feature is not None and feature.kind == "cylinder", feature
    st.state.picks["part"] = ("carrier", feature)
    st.grasps.f_from.value = "from +z"
    act(st, st.grasps.on_add)
    grasps = st.asm.parts["carrier"].grasps
    assert [g.name for g in grasps] == ["shaft", "grasp"] and st.grasps.f_grasp.value == "grasp"
    assert abs(grasps[1].width - 0.008) < 2e-4  # the shaft's diameter
    np.testing.assert_allclose(grasps[1].T_part_gripper[:3, 2], (0, 0, -1), atol=1e-9)  # the gripper comes down
    act(st, lambda c: st.undo_redo("Undo", c))
    assert [g.name for g in st.asm.parts["carrier"].grasps] == ["shaft"]
    act(st, lambda c: st.undo_redo("Redo", c))
    st.grasps.f_grasp.value = "shaft"
    act(st, st.grasps.on_delete)
    assert [g.name for g in st.asm.parts["carrier"].grasps] == ["grasp"]
    from apose_studio.assembly.model import save_assembly

    save_assembly(st.asm, tmp_path / "pr" / "again.yaml")
    assert [g.name for g in load_assembly(tmp_path / "pr" / "again.yaml").parts["carrier"].grasps] == ["grasp"]
    st.steps.step_index = None
    st.refresh_assembly_widgets()
    assert "/assembly/gripper/place" not in st.nodes


def test_play_sequence_carries_each_part_in_the_gripper(studio):
    import time

    from apose_studio.studio.grasps_panel import CARRY

    st = studio(SAMPLES / "planetary_reducer" / "assembly.yaml")
    seen = []
    original = st.grasps.carry

    def spy(pid, T):
        original(pid, T)
        g = st.asm.parts[pid].grasps[0]
        seen.append((pid, np.asarray(st.nodes[CARRY].position) - (T @ g.T_part_gripper)[:3, 3]))

    st.grasps.carry = spy
    act(st, st.steps.on_play_sequence)
    t0 = time.time()
    while time.time() - t0 < 60 and not (seen and seen[-1][0] == "cover" and CARRY not in st.nodes):
        time.sleep(0.1)
    assert [p for p in dict.fromkeys(p for p, _ in seen)] == ["sun_gear", "housing", "carrier", "cover"]
    assert max(np.abs(d).max() for _, d in seen) < 1e-6  # the gripper where the grasp puts it on the moving part
    assert CARRY not in st.nodes  # put away after the last step


def test_an_estimate_shows_the_gripper_where_it_places_the_part(studio, tmp_path):
    """Inspect: with a grasp in the assembly, the estimate's part is drawn held by the gripper (legend, layer)."""
    from apose_studio.assembly.model import load_assembly
    from apose_studio.geometry import se3
    from apose_studio.synth.frame import RenderSettings
    from apose_studio.synth.render import render_dataset

    asm_path = SAMPLES / "planetary_reducer" / "assembly.yaml"
    render_dataset(load_assembly(asm_path), tmp_path / "ds", RenderSettings(frames=1, seed=4, base_pose="fixed"),
                   steps=[3], progress=False)
    st = studio(asm_path, tmp_path / "ds")
    assert "/inspect/gripper" not in st.nodes  # nothing estimated yet
    st.inspect.i_prior.value = True
    act(st, st.inspect.run_estimation, False)
    r = st.inspect.result
    assert r is not None and r.ok, st.notes
    h = st.nodes["/inspect/gripper"]
    G = st.state.inspect_assembly().parts["carrier"].grasps[0].T_part_gripper
    T = se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(h.wxyz)), np.asarray(h.position))
    np.testing.assert_allclose(T, r.T_world_part @ G, atol=1e-5)
    assert "gripper" in st.results.i_legend.content
    place = [n for n, layer in st.results._label_layers.items() if layer == "gripper"]
    assert place and all(st.nodes[n].visible for n in place)  # its label, "place"
    st.results.layers["gripper"].value = False
    st.results.apply_layers()
    assert not st.nodes["/inspect/gripper"].visible
    assert not any(st.nodes[n].visible for n in place)  # a label goes with what it names
    assert st.nodes[next(n for n, layer in st.results._label_layers.items() if layer == "boxes")].visible

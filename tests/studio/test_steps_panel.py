"""The Steps folder: the gizmo's drag events (tests/e2e drags it with the mouse)."""


import numpy as np
import pytest

from apose_studio.geometry import se3

from .conftest import act, errors


@pytest.fixture
def through_allowed(monkeypatch):
    """For tests of other behaviour that type poses inside the casing (z = 0): no 'Parts go through' warning."""
    from apose_studio.studio import authoring

    monkeypatch.setattr(authoring, "PENETRATION_SHARE", 2.0)


def test_gizmo_drag_updates_the_typed_pose_with_snapping(studio, gearbox_copy):
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_assembly_scene()
    g = st.nodes["/assembly/gizmo"]
    T_world_base = st.steps._preview["casing"]
    T = T_world_base @ se3.make_T(se3.euler_deg_to_matrix([0, 0, 31.0], "xyz"), np.array([0.01234, 0.0, 0.0147]))
    g._impl.wxyz, g._impl.position = se3.matrix_to_quat_wxyz(T[:3, :3]), T[:3, 3]
    from viser._scene_handles import TransformControlsEvent  # what viser passes (tests/e2e drags with the mouse)

    for cb in g._impl_aux.update_cb:
        cb(TransformControlsEvent(client=None, client_id=None, target=g, phase="update"))
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.0125, 0, 0.0145], atol=1e-9)  # moves at once
    for cb in g._impl_aux.update_cb:
        cb(TransformControlsEvent(client=None, client_id=None, target=g, phase="end"))
    assert errors(st) == []
    np.testing.assert_allclose(st.steps.f_t.value, (12.5, 0.0, 14.5), atol=1e-6)  # snapped to 0.5 mm
    np.testing.assert_allclose(st.steps.f_r.value, (0.0, 0.0, 30.0), atol=1e-6)  # and to 5°
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.0125, 0, 0.0145], atol=1e-9)



def _drag(g, phase: str) -> None:
    from viser._scene_handles import TransformControlsEvent  # what viser passes (tests/e2e drags with the mouse)

    for cb in g._impl_aux.update_cb:
        cb(TransformControlsEvent(client=None, client_id=None, target=g, phase=phase))


def _shown(handle) -> np.ndarray:
    """A scene node's pose as the page is told it (world)."""
    return se3.make_T(se3.quat_wxyz_to_matrix(np.asarray(handle.wxyz)), np.asarray(handle.position))


def test_a_typed_pose_moves_the_gizmo_and_the_next_drag_starts_there(studio, gearbox_copy, through_allowed):
    """#28: type x = 30 on a step, then drag the gizmo's z arrow: the translation becomes (30, 0, z), not
    (0, 0, z) from where the gizmo was before the typing."""
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_assembly_scene()
    st.steps.f_snap_mm.value, st.steps.f_snap_deg.value = 0.0, 0.0
    g = st.nodes["/assembly/gizmo"]
    st.steps.f_t.value = (30.0, 0.0, 0.0)  # typing fires the same callback as the browser
    T_world_base = st.steps._preview["casing"]
    want = T_world_base @ st.asm.steps[0].T_base_part
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.030, 0, 0], atol=1e-12)
    np.testing.assert_allclose(_shown(g), want, atol=1e-6)  # the gizmo went with the part
    np.testing.assert_allclose(_shown(st.steps.mesh_handles["pinion"]), want, atol=1e-6)
    up = want.copy()
    up[:3, 3] += T_world_base[:3, 2] * 0.02  # the z arrow, 20 mm along the base's z
    g._impl.wxyz, g._impl.position = se3.matrix_to_quat_wxyz(up[:3, :3]), up[:3, 3]
    _drag(g, "start")
    _drag(g, "end")
    assert errors(st) == []
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [0.030, 0, 0.020], atol=1e-6)
    np.testing.assert_allclose(st.steps.f_t.value, (30.0, 0.0, 20.0), atol=1e-3)


def test_undo_and_redo_move_the_drawn_part_and_the_gizmo_with_the_draft(studio, gearbox_copy, through_allowed):
    """#28: after Undo the fields and the gizmo said (0, 0, 0) while the part stayed drawn at the typed pose."""
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_assembly_scene()
    before = st.asm.steps[0].T_base_part.copy()
    st.steps.f_t.value = (30.0, 0.0, 0.0)
    for which, T_base_part in (("Undo", before), ("Redo", st.asm.steps[0].T_base_part.copy())):
        act(st, st.undo_redo, which)
        np.testing.assert_allclose(st.asm.steps[0].T_base_part, T_base_part, atol=1e-12)
        want = st.steps._preview["casing"] @ T_base_part
        np.testing.assert_allclose(_shown(st.steps.mesh_handles["pinion"]), want, atol=1e-6)  # the drawn part
        np.testing.assert_allclose(_shown(st.nodes["/assembly/gizmo"]), want, atol=1e-6)
        np.testing.assert_allclose(st.steps.f_t.value, T_base_part[:3, 3] * 1000, atol=1e-3)
    assert errors(st) == []


def test_a_one_axis_drag_snaps_only_what_it_moved(studio, gearbox_copy):
    """#28: dragging the x arrow re-snapped y and z. A typed y = 0.3 mm and z = 14.7 mm stay as typed while
    the drag moves x, which snaps to the 0.5 mm step."""
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_assembly_scene()
    st.steps.f_t.value = (0.0, 0.3, 14.7)
    st.steps.f_r.value = (0.0, 0.0, 12.0)  # not a multiple of the 5° step either
    g = st.nodes["/assembly/gizmo"]
    T = _shown(g)
    T[:3, 3] += st.steps._preview["casing"][:3, 0] * 0.01234  # along the base's x
    g._impl.wxyz, g._impl.position = se3.matrix_to_quat_wxyz(T[:3, :3]), T[:3, 3]
    _drag(g, "start")
    _drag(g, "end")
    assert errors(st) == []
    np.testing.assert_allclose(st.steps.f_t.value, (12.5, 0.3, 14.7), atol=1e-3)
    np.testing.assert_allclose(st.steps.f_r.value, (0.0, 0.0, 12.0), atol=1e-3)


def test_faceted_cad_keeps_its_edges_and_round_parts_stay_smooth(studio, gearbox_copy):
    """#28: shared vertices averaged a box's normals across its edges and faceted CAD looked melted. A box is
    drawn with its six faces apart (4 corners each); a cylinder's side keeps its vertices shared (smooth);
    the parts sent to the page are drawn that way."""
    import trimesh

    from apose_studio.studio.widgets import shaded

    v, f = shaded(trimesh.creation.box((1, 2, 3)))
    assert len(f) == 12 and len(v) == 24
    cyl = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=64)
    v, f = shaded(cyl)
    assert len(v) < 2 * len(cyl.vertices)  # the side's 64 columns share vertices; only the rims are split
    st = studio(gearbox_copy)
    sent = st.steps.mesh_handles["casing"]
    assert len(sent.vertices) == len(shaded(st.model("casing", st.asm).mesh)[0]) > len(st.model("casing", st.asm).mesh.vertices)


def test_the_status_says_whether_the_draft_is_saved(studio, gearbox_copy, tmp_path, through_allowed):
    """#28: the status said "Saved" after edits. It says "Unsaved changes" once the draft differs from what
    was opened or saved, "Opened from ... no changes" again after Undo back to it (never "Saved" for a file
    only opened: a newcomer read it as the studio having written their file), "Saved as" after a Save, and
    "Not saved yet" for New."""
    st = studio(gearbox_copy)
    status = st.steps.status_md.content
    assert "Saved as" not in status and "no changes" in status and str(gearbox_copy.name) in status, status
    st.steps.step_index = 0
    st.steps.f_t.value = (30.0, 0.0, 0.0)
    assert "Unsaved changes** (opened from" in st.steps.status_md.content
    act(st, st.undo_redo, "Undo")
    assert "Unsaved changes" not in st.steps.status_md.content and "Opened from" in st.steps.status_md.content
    act(st, st.undo_redo, "Redo")
    assert "Unsaved changes" in st.steps.status_md.content
    act(st, st.files.on_save)
    assert errors(st) == [] and "Unsaved changes" not in st.steps.status_md.content
    assert "Saved as" in st.steps.status_md.content
    st.files.f_path.value = str(tmp_path / "fresh.yaml")
    act(st, st.files.on_new)
    assert "Not saved yet" in st.steps.status_md.content


def test_the_keystrokes_of_a_typed_number_are_one_undo_step(studio, gearbox_copy):
    """#28 (newcomer): typing 30 recorded "3" and "30" as two undo steps (and Undo stopped at 3 mm). Edits of
    one field in quick succession are one step; another field, or a pause, starts the next."""
    from apose_studio.studio.authoring import History

    st = studio(gearbox_copy)
    st.steps.step_index = 0
    before = st.asm.steps[0].T_base_part.copy()
    st.steps.f_t.value = (3.0, 0.0, 14.5)
    st.steps.f_t.value = (30.0, 0.0, 14.5)
    act(st, st.undo_redo, "Undo")
    np.testing.assert_allclose(st.asm.steps[0].T_base_part, before, atol=1e-12)
    h, a, b, c = History(), object(), object(), object()
    h.record(a, typing="x", now=0.0)
    h.record(b, typing="x", now=1.0)  # the same field, 1 s later: the same step
    assert h.undo_stack == [a]
    h.record(b, typing="x", now=4.0)  # after a pause: a new step
    assert h.undo_stack == [a, b]
    h.record(c, typing="y", now=4.5)  # another field: a new step
    h.record(a, now=4.6)  # an edit that is not typing
    assert h.undo_stack == [a, b, c, a]


def test_the_base_is_chosen_from_the_parts_in_place(studio, gearbox_copy):
    """Base parts are ticked from the parts in place before the step (not typed); the pose's frame part is
    chosen from a list, and choosing another keeps the part where it is."""
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_steps()
    assert list(st.steps.base_boxes) == ["casing"]  # step 1 places the pinion: only the casing is in place
    st.steps.step_index = 1
    st.steps.refresh_steps()
    boxes = st.steps.base_boxes
    assert list(boxes) == ["casing", "pinion"] and boxes["casing"].value and boxes["pinion"].value
    assert boxes["casing"].disabled and not boxes["pinion"].disabled  # the frame part stays in the base
    T_root_wheel = st.asm.T_root_part("wheel")
    st.steps.base_boxes["pinion"].value = False
    assert st.asm.steps[1].base == ("casing",) and not errors(st)
    st.steps.base_boxes["pinion"].value = True
    assert st.asm.steps[1].base == ("casing", "pinion")
    st.steps.f_base_frame.value = "pinion"
    assert st.asm.steps[1].base == ("pinion", "casing") and not errors(st)
    np.testing.assert_allclose(st.asm.T_root_part("wheel"), T_root_wheel, atol=1e-12)  # the wheel did not move
    assert st.steps.base_boxes["pinion"].disabled and not st.steps.base_boxes["casing"].disabled
    act(st, st.undo_redo, "Undo")
    assert st.asm.steps[1].base == ("casing", "pinion")


def test_a_typed_pose_far_beyond_the_parts_is_kept_and_said(studio, gearbox_copy, through_allowed):
    """1,000,000 typed for a translation in mm (a value in metres or a slip) is kept, but a warning names
    the step, the distance and the sizes; a pose near the parts says nothing."""
    st = studio(gearbox_copy)
    st.steps.step_index = 0
    st.steps.refresh_steps()
    st.steps.f_t.value = (30.0, 0.0, 14.5)
    assert not errors(st)
    st.steps.f_t.value = (1e6, 0.0, 14.5)
    np.testing.assert_allclose(st.asm.steps[0].T_base_part[:3, 3], [1000.0, 0.0, 0.0145])
    (title, body, _), = errors(st)
    assert title == "Pose looks wrong" and "step 1 puts pinion 1e+06 mm from the origin of casing" in body


def test_framing_follows_the_step_and_the_units(studio, gearbox_copy):
    """Assembly framing shows the selected step's part and the sub-assembly it goes on, not a part waiting
    aside; a units change (the parts 1000x larger) frames them anew."""
    import trimesh

    st = studio(gearbox_copy)
    trimesh.creation.box((30.0, 30.0, 30.0)).export(gearbox_copy.parent / "spare.stl")
    st.files.f_mesh.value = str(gearbox_copy.parent / "spare.stl")
    act(st, st.files.on_add_parts)
    assert "spare" in st.asm.parts and "spare" in st.steps._preview

    def framed():
        cam = st.server.initial_camera
        return np.asarray(cam.look_at, float), float(np.linalg.norm(np.asarray(cam.position) - np.asarray(cam.look_at)))

    st.show_view("Assembly")
    st.steps.step_index = None
    st.frame_camera_on_assembly()
    _, d_all = framed()
    st.steps.step_index = 0
    st.frame_camera_on_assembly()
    centre, d_step = framed()
    assert d_step < d_all  # tighter: the spare part waiting aside is not in the frame
    spare = st.steps._preview["spare"][:3, 3]
    assert np.linalg.norm(spare - centre) > d_step * np.tan(np.radians(25.0))  # outside the view's half-angle
    st.files.f_units.value = "m"
    assert st.asm.units == "m"
    _, d_m = framed()
    assert d_m > 100 * d_step


def test_a_typed_pose_through_the_base_is_kept_and_said(studio, gearbox_copy):
    """Typing x = 30 mm for the wheel puts it through the casing's wall: the pose is kept and a warning names
    the base part and how much of the wheel is inside; the sample's own poses (touching, not inside) say
    nothing."""
    st = studio(gearbox_copy)
    st.steps.step_index = 1
    st.steps.refresh_steps()
    st.steps.f_t.value = (16.0, 0.0, 14.5)  # the sample's own pose, typed
    assert not errors(st)
    st.steps.f_t.value = (30.0, 0.0, 14.5)
    np.testing.assert_allclose(st.asm.steps[1].T_base_part[:3, 3], [0.030, 0.0, 0.0145])
    (title, body, _), = errors(st)
    assert title == "Parts go through each other" and "step 2 puts wheel inside casing:" in body, body


def test_no_sample_step_goes_through_its_base():
    """The check's thresholds against every sample assembly as authored: no step is flagged."""
    from apose_studio.assembly.mesh import load_parts
    from apose_studio.assembly.model import load_assembly
    from apose_studio.studio import authoring

    from ..conftest import SAMPLES

    for path in sorted(SAMPLES.glob("*/assembly.yaml")):
        asm = load_assembly(path)
        models = load_parts(asm)
        for i in range(len(asm.steps)):
            assert authoring.penetrations(asm, i, models) == [], (path.parent.name, i + 1)

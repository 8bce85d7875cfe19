"""The Steps folder: the gizmo's drag events (tests/e2e drags it with the mouse)."""


import numpy as np

from apose_studio.geometry import se3

from .conftest import errors


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


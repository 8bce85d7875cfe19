"""What a page sends is checked on the server before anything acts on it (safety round 2, #24 re-test):
M-d (a dropdown set to a path outside the workspace), M-g (one tab's camera broke another tab's Open),
and the minors (NaN in a slider or colour, values outside a dropdown's options, flipped `disabled`).

A raw websocket speaks viser's protocol as a hostile page would (msgpack messages; viser runs a tab's
callbacks once it has reported its camera)."""

import math
import time

import msgspec
import numpy as np
import pytest

from ..conftest import SAMPLES
from .conftest import act, errors

GEARBOX = SAMPLES / "helical_gearbox" / "assembly.yaml"
CAMERA = dict(type="ViewerCameraMessage", wxyz=[1.0, 0.0, 0.0, 0.0], position=[0.5, -0.5, 0.4], fov=0.9, near=0.01,
              far=100.0, image_height=600, image_width=800, look_at=[0.0, 0.0, 0.0], up_direction=[0.0, 0.0, 1.0])


def wait(cond, timeout=10.0):
    t0 = time.time()
    while time.time() - t0 < timeout and not cond():
        time.sleep(0.02)
    return cond()


class Tab:
    """A page of the studio as a raw websocket: connected, its camera reported, its client id known."""

    def __init__(self, st, camera=None):
        import viser
        import websockets.sync.client

        self.st = st
        host_port, path = st.url.split("//", 1)[1].split("/", 1)
        before = set(st.server.get_clients())
        self.ws = websockets.sync.client.connect(f"ws://{host_port}/{path}", origin=f"http://{host_port}",
                                                 subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
                                                 max_size=None)
        self.send(**(camera or CAMERA))
        assert wait(lambda: set(st.server.get_clients()) - before), "the tab never counted as connected"
        self.client_id = max(set(st.server.get_clients()) - before)

    @property
    def client(self):
        return self.st.server.get_clients()[self.client_id]

    @property
    def view(self):
        """The studio this tab drives: its own (a studio serving tabs of their own: `serve(tabs=True)`), else the
        one studio on the server's GUI."""
        from apose_studio.studio.desk import Desk

        if not isinstance(self.st, Desk):
            return self.st
        views = self.st.views
        assert wait(lambda: self.client_id in views), "the tab never got a studio of its own"
        return views[self.client_id]

    def send(self, **message):
        self.ws.send(msgspec.msgpack.encode(message))

    def set(self, handle, **updates):
        self.send(type="GuiUpdateMessage", uuid=handle._impl.uuid, updates=updates)

    def settle(self):
        """Wait until every message sent before has been dispatched: a valid update sent last is applied."""
        probe = self.view.results.i_full  # a checkbox always shown (a Layers one is hidden while its layer is empty)
        want = not probe.value
        self.set(probe, value=want)
        assert wait(lambda: probe.value == want)
        time.sleep(0.3)  # callbacks run on viser's thread pool

    def close(self):
        self.ws.close()


def inputs(st):
    return list(st.server.gui._gui_input_handle_from_uuid.values())


def hostile_values(handle):
    """Values a page may not give this widget, by its kind."""
    import viser

    nan, inf = float("nan"), float("inf")
    junk = [None, {"a": 1}, nan]
    if isinstance(handle, viser.GuiButtonHandle):
        return [False, 1, "x", *junk]
    if isinstance(handle, (viser.GuiDropdownHandle, viser.GuiButtonGroupHandle)):
        return ["/etc/shadow", "../../../etc/passwd", "", "x" * 100_000, 5, *junk]
    if isinstance(handle, viser.GuiCheckboxHandle):
        return [1, "true", *junk]
    if isinstance(handle, viser.GuiTextHandle):
        return [5, "x" * 70_000, "a\nb", "nul\x00", *junk]
    if isinstance(handle, (viser.GuiNumberHandle, viser.GuiSliderHandle)):
        out = [inf, -inf, 1e308, -1e308, "5", True, [1.0], 2.0 ** 80, *junk]
        if handle.max is not None:
            out.append(float(handle.max) + 1.0)
        if handle.min is not None:
            out.append(float(handle.min) - 1.0)
        if isinstance(handle.value, int):
            out.append(0.5)
        return out
    if isinstance(handle, (viser.GuiVector2Handle, viser.GuiVector3Handle)):
        n = len(handle.value)
        return [[nan] * n, [inf] * n, [1e308] * n, [0.0] * (n - 1), [0.0] * (n - 1) + ["x"], "abc", *junk]
    if isinstance(handle, viser.GuiRgbHandle):
        return [[nan] * 3, [300, 0, 0], [-1, 0, 0], [1.5, 0, 0], [0, 0], "#ff0000", *junk]
    return ["x", True, 1.0, *junk]  # upload buttons, progress bars: no value from the page


def same(a, b):
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def send_hostile_values(tab, handles) -> tuple[list, dict]:
    """Every value each widget does not allow, sent by `tab` (the probe `Tab.settle` sets left out); returns the
    widgets and their values before."""
    handles = [h for h in handles if h is not tab.view.results.i_full]
    before = {h._impl.uuid: h.value for h in handles}
    for h in handles:
        for v in hostile_values(h):
            tab.set(h, value=v)
    return handles, before


def changed(handles, before) -> list:
    """(label, before, now) of each widget whose value is not what it was."""
    return [(getattr(h, "label", type(h).__name__), before[h._impl.uuid], h.value) for h in handles
            if not same(before[h._impl.uuid], h.value)]


def test_every_widget_takes_only_what_it_allows(studio, gearbox_dataset, capfd):
    """Every input of the studio (dropdowns, text, numbers, sliders, colours, checkboxes, vectors, buttons)
    keeps its value against values it does not allow, nothing raises, and the tab is told."""
    st = studio(GEARBOX, gearbox_dataset)
    tab = Tab(st)
    handles, before = send_hostile_values(tab, inputs(st))
    tab.settle()
    assert not changed(handles, before)
    assert not [n for n in st.notes if "internal error" in n[1]]
    assert any(n[1].startswith("ignored: ") for n in errors(st))  # told (at most once a second)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "cannot convert float NaN" not in err
    tab.close()


def test_the_reported_attack_mask_set_to_a_server_path(studio, gearbox_dataset, tmp_path, monkeypatch):
    """M-d as reported: Mask set to /etc/shadow (or a file outside --root) and Estimate frame pressed. The
    value is refused, the estimate runs with the mask that was chosen in the page, and no file outside
    the workspace is opened (nor does a reply say whether it exists)."""
    outside = tmp_path.parent / f"{tmp_path.name}-outside"
    outside.mkdir()
    (outside / "secret.pt").write_bytes(b"not a model")
    st = studio(GEARBOX, gearbox_dataset)
    used = []

    def estimate(job, im_id):
        used.append(job.mask)
        raise AssertionError("enough")

    monkeypatch.setattr(st.inspect, "estimate", estimate)
    tab = Tab(st)
    for path in ("/etc/shadow", "/root/.bashrc", str(outside / "secret.pt"), str(outside / "missing.pt")):
        time.sleep(1.05)  # one notice a second per tab
        tab.set(st.inspect.i_mask, value=path)
        tab.settle()
        assert st.inspect.i_mask.value == "gt"
        assert errors(st) and "is not one of its choices" in errors(st)[-1][1] and repr(path)[:15] in errors(st)[-1][1]
    run = next(h for h in inputs(st) if getattr(h, "label", "") == "Run")
    tab.set(run, value="Estimate frame")
    assert wait(lambda: used)
    assert used == ["gt"]
    assert not [n for n in st.notes if "not a readable model" in n[1] or "no such model" in n[1]]
    tab.close()


def test_a_mask_model_is_confined_where_it_is_used(studio, gearbox_dataset, tmp_path):
    """Whatever puts a model path among the Mask choices, the estimate resolves it through the workspace
    again: a file outside is refused before it is opened."""
    st = studio(GEARBOX, gearbox_dataset)
    outside = tmp_path.parent / f"{tmp_path.name}-elsewhere" / "model.pt"
    st.inspect.i_mask.options = list(st.inspect.i_mask.options) + [str(outside)]
    st.inspect.i_mask.value = str(outside)
    with pytest.raises(Exception, match="outside the studio's workspace"):
        st.inspect.job(st.inspect.current_step(), [st.inspect.frame.im_id])
    before = len(st.notes)
    act(st, st.inspect.run_estimation, False)
    assert "outside the studio's workspace" in st.notes[-1][1] and len(st.notes) > before
    for source in ("gt", "depth", "box", "prompt"):
        assert st.inspect.confined_mask(source) == source


def test_disabled_and_hidden_widgets_take_no_input_and_props_stay_the_servers(studio, gearbox_dataset):
    st = studio(GEARBOX, gearbox_dataset)
    tab = Tab(st)
    masks = tuple(st.inspect.i_mask.options)
    stage = st.results.i_stage
    stage.disabled = True
    tab.set(stage, value=2)  # a disabled slider
    units = st.files.f_units
    units.visible = False
    tab.set(units, value="cm")  # a hidden dropdown
    part = st.files.f_part
    folder = st.server.gui._container_handle_from_uuid[part._impl.parent_container_id]
    folder.visible = False
    other = next(p for p in st.asm.parts if p != part.value)
    tab.set(part, value=other)  # a dropdown in a hidden folder
    tab.set(stage, disabled=False)  # a page may not enable what the server disabled
    tab.set(stage, value=2, update_cb=[])
    tab.set(units, visible=True)
    tab.set(st.inspect.i_mask, options=["/etc/shadow"])
    tab.settle()
    assert stage.value == 1 and stage.disabled
    assert units.value == "mm" and not units.visible and st.asm.units == "mm"
    assert part.value != other
    assert tuple(st.inspect.i_mask.options) == masks and "/etc/shadow" not in masks
    folder.visible, units.visible = True, True
    tab.set(units, value="cm")  # shown again: the page's input counts
    assert wait(lambda: st.asm.units == "cm")
    tab.close()


def test_a_degenerate_camera_report_is_ignored_and_open_works_for_another_tab(studio, gearbox_copy):
    """M-g as reported: a tab whose camera reports position == look_at (or NaN) made Open fail with
    "internal error" for whoever pressed it. Such reports are dropped; Open works and moves every camera."""
    st = studio(root=gearbox_copy.parent)
    bad = Tab(st)
    for report in (dict(CAMERA, position=[0.0, 0.0, 0.0], look_at=[0.0, 0.0, 0.0]),
                   dict(CAMERA, position=[float("nan")] * 3), dict(CAMERA, wxyz=[0.0, 0.0, 0.0, 0.0]),
                   dict(CAMERA, fov=float("nan")), dict(CAMERA, image_height=0), dict(CAMERA, up_direction=[0, 0, 0]),
                   dict(CAMERA, position="x")):
        bad.send(**report)
    bad.settle()
    cam = bad.client.camera
    np.testing.assert_allclose(cam.position, CAMERA["position"])
    assert cam.fov == pytest.approx(0.9) and cam.image_height == 600
    st.files.f_path.value = str(gearbox_copy)
    act(st, st.files.on_open)
    assert not errors(st), errors(st)
    assert "casing" in st.asm.parts
    assert not np.allclose(bad.client.camera.position, CAMERA["position"])  # moved to frame the assembly
    bad.close()


def test_one_camera_that_cannot_be_moved_never_breaks_the_others(studio, gearbox_copy):
    """Guarded per tab: even a camera state that went bad by another way leaves the other tabs' cameras
    (and a new tab's) framed, and the action succeeds."""
    st = studio(root=gearbox_copy.parent)
    broken, fine = Tab(st), Tab(st)
    state = broken.client.camera._state
    state.position, state.look_at = np.zeros(3), np.zeros(3)  # what the reported attack left behind
    start = np.array(st.server.initial_camera.position, float)
    st.files.f_path.value = str(gearbox_copy)
    act(st, st.files.on_open)
    assert not errors(st), errors(st)
    assert not np.allclose(fine.client.camera.position, CAMERA["position"])
    assert not np.allclose(st.server.initial_camera.position, start)  # a new tab's camera is framed too
    broken.close()
    fine.close()


def test_gizmo_and_pointer_reports_must_be_finite_and_from_a_shown_gizmo(studio):
    st = studio(GEARBOX)
    tab = Tab(st)
    clicks = []
    tab.client.scene.on_click()(lambda e: clicks.append(e))
    pose = st.asm.steps[0].T_base_part.copy()
    assert "/assembly/gizmo" in st.nodes
    nan = float("nan")
    for wxyz, position in (([nan, 0, 0, 0], [0, 0, 0]), ([1, 0, 0, 0], [nan, 0, 0]), ([0, 0, 0, 0], [0, 0, 0]),
                           ([2, 0, 0, 0], [0, 0, 0]), ([1, 0, 0, 0], [1e300, 0, 0])):
        tab.send(type="TransformControlsUpdateMessage", name="/assembly/gizmo", wxyz=wxyz, position=position, owner="")
    for origin, direction in (([nan, 0, 0], [0, 0, 1]), ([0, 0, 0], [0, 0, 0]), ([0, 0, 0], "x")):
        tab.send(type="ScenePointerMessage", event_type="click", ray_origin=origin, ray_direction=direction,
                 screen_pos=[[0.5, 0.5]], modifier=None)
    tab.send(type="ScenePointerMessage", event_type="rect-select", ray_origin=None, ray_direction=None,
             screen_pos=[[nan, 0.1], [0.5, 0.5]], modifier=None)
    tab.settle()
    np.testing.assert_array_equal(st.asm.steps[0].T_base_part, pose)
    assert np.isfinite(st.nodes["/assembly/gizmo"].position).all() and not clicks
    act(st, lambda c: st.show_view("Inspect"))  # the gizmo is hidden: its drags are not the page's to make
    tab.send(type="TransformControlsUpdateMessage", name="/assembly/gizmo", wxyz=[1, 0, 0, 0], position=[0.1, 0.2, 0.3],
             owner="")
    tab.settle()
    np.testing.assert_array_equal(st.asm.steps[0].T_base_part, pose)
    act(st, lambda c: st.show_view("Assembly"))
    tab.send(type="ScenePointerMessage", event_type="click", ray_origin=[0, 0, 1], ray_direction=[0, 0, -1],
             screen_pos=[[0.5, 0.5]], modifier=None)
    assert wait(lambda: clicks)  # an honest click still arrives
    tab.close()


def test_messages_the_studio_never_asks_for_are_dropped(studio, monkeypatch):
    """A share URL (a public tunnel to the studio), uploads into a text field, parts for another tab's
    upload, and message types viser only sends to pages."""
    st = studio()
    asked = []
    monkeypatch.setattr(st.server, "request_share_url", lambda *a, **k: asked.append(1))
    a, b = Tab(st), Tab(st)
    a.send(type="ShareUrlRequest")
    text = st.files.f_path._impl.uuid
    a.send(type="FileTransferStartUpload", source_component_uuid=text, transfer_uuid="t-text", filename="x.stl",
           mime_type="model/stl", part_count=1, size_bytes=5)
    button = st.files.upload._impl.uuid
    a.send(type="FileTransferStartUpload", source_component_uuid=button, transfer_uuid="t-a", filename="x.stl",
           mime_type="model/stl", part_count=1, size_bytes=2000)
    a.settle()
    states = st.server.gui._current_file_upload_states
    assert "t-text" not in states and "t-a" in states
    b.send(type="FileTransferPart", source_component_uuid=button, transfer_uuid="t-a", part_index=0, content=b"\0" * 2000)
    b.send(type="FileTransferStartUpload", source_component_uuid=button, transfer_uuid="t-b", filename="y.stl",
           mime_type="model/stl", part_count=1, size_bytes=-5)
    b.send(type="RemoveNotificationMessage", uuid="x")  # a type viser only ever sends to pages
    b.settle()
    assert states["t-a"]["transferred_bytes"] == 0 and "t-b" not in states
    st.files.upload.disabled = True
    a.send(type="FileTransferStartUpload", source_component_uuid=button, transfer_uuid="t-c", filename="z.stl",
           mime_type="model/stl", part_count=1, size_bytes=10)
    a.settle()
    assert "t-c" not in states and not asked
    # a message viser cannot even decode (NaN for a whole number) ends that tab's connection, no other's
    c = Tab(st)
    c.send(type="FileTransferStartUpload", source_component_uuid=button, transfer_uuid="t-d", filename="y.stl",
           mime_type="model/stl", part_count=float("nan"), size_bytes=10)
    assert wait(lambda: c.client_id not in st.server.get_clients())
    a.settle()
    b.settle()
    a.close()
    b.close()


def test_value_rules_unit():
    """The rules themselves, on widgets of a bare viser server (no studio)."""
    import viser

    from apose_studio.studio.viser_adapter import input_problem, scene_problem, value_problem

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        gui = server.gui
        dd = gui.add_dropdown("D", ("a", "b"))
        n = gui.add_number("N", 1.0, min=0.0, max=10.0)
        free = gui.add_number("F", 1.0)
        sl = gui.add_slider("S", 0, 4, 1, 0)
        v = gui.add_vector3("V", (0.0, 0.0, 0.0), min=(-1.0, -1.0, -1.0), max=(1.0, 1.0, 1.0))
        rgb = gui.add_rgb("C", (1, 2, 3))
        t = gui.add_text("T", "")
        assert value_problem(dd, "b") is None and "not one of its choices" in value_problem(dd, "c")
        assert value_problem(n, 10) is None and "above its maximum 10" in value_problem(n, 10.5)
        assert "not a finite number" in value_problem(free, float("nan")) and value_problem(free, -1e9) is None
        assert "beyond" in value_problem(free, 1e300)
        assert value_problem(sl, 4) is None and "whole number" in value_problem(sl, 2.5)
        assert value_problem(v, [1, -1, 0.5]) is None and "[2] 2 is above" in value_problem(v, [0, 0, 2])
        assert value_problem(rgb, [255, 0, 7]) is None and "[0] 256 is above" in value_problem(rgb, [256, 0, 0])
        assert value_problem(t, "a path/with spaces") is None and "control or invisible character" in value_problem(t, "a\x1bb")
        for c in "\n\r\x85\u2028\u2029\u202e\u200b\ufeff\x00":  # line breaks of every kind, bidi, invisible
            assert "control or invisible character" in value_problem(t, f"name{c}x"), repr(c)
        assert value_problem(t, "Zahnradgetriebe é 字 tab\there") is None
        m = gui.add_text("M", "", multiline=True)
        assert value_problem(m, "two\nlines\r\n") is None and "invisible" in value_problem(m, "a\u202eb")
        assert "value only, not disabled" in input_problem(gui, dd, {"disabled": False})
        dd.disabled = True
        assert input_problem(gui, dd, {"value": "a"}) == "it is disabled"
    finally:
        server.stop()
    from viser import _messages as m

    ok = m.ViewerCameraMessage(**{k: v for k, v in CAMERA.items() if k != "type"})
    assert scene_problem(ok) is None
    assert "look-at" in scene_problem(m.ViewerCameraMessage(**{**ok.__dict__, "look_at": tuple(CAMERA["position"])}))


def test_a_typed_prompt_with_an_infinite_number_is_bad_input_not_a_bug(studio, gearbox_dataset):
    """Found attacking the fix: 'Prompt (px)' = 1e309,1e309,1e309,1e309 (valid text) was an internal error."""
    st = studio(GEARBOX, gearbox_dataset)
    for text in ("1e309,1e309,1e309,1e309", "1e309,5", "nan,1,2,3", "x" * 5000):
        st.prompt.i_prompt.value = text
        assert errors(st) and "internal error" not in errors(st)[-1][1] and len(errors(st)[-1][1]) < 300, errors(st)[-1]


def test_a_tab_s_own_dialog_takes_input_from_that_tab_only(studio, gearbox_copy):
    """Widgets made for one tab (the Replace dialog) are screened at that tab's own dispatcher: another tab
    that names the button does nothing, the tab itself replaces the file."""
    import shutil

    other = gearbox_copy.parent / "other.yaml"
    shutil.copy(gearbox_copy, other)
    st = studio(gearbox_copy, root=gearbox_copy.parent)
    a, b = Tab(st), Tab(st)
    st.files.f_path.value = str(other)
    save = next(h for h in inputs(st) if getattr(h, "label", "") == "File actions")
    a.set(save, value="Save")
    own = a.client.gui._gui_input_handle_from_uuid
    assert wait(lambda: any(getattr(h, "label", "") == "Replace" for h in own.values()))
    replace = next(h for h in own.values() if getattr(h, "label", "") == "Replace")
    before = other.read_bytes()
    b.set(replace, value=True)
    b.settle()
    assert other.read_bytes() == before and not (other.parent / "other.yaml.bak").exists()
    a.set(replace, value=True)
    assert wait(lambda: (other.parent / "other.yaml.bak").exists())
    a.close()
    b.close()


def test_a_page_image_is_taken_only_as_a_png_or_jpeg_of_sane_size():
    """The page's image of its 3D view (Download image) reaches the decoder only as a PNG or JPEG whose
    header gives at most 8192 px a side: a small file claiming 60000 x 60000 px (gigabytes once unpacked)
    or other bytes are refused."""
    import cv2

    from apose_studio.studio.viser_adapter import image_size, render_payload_problem

    img = np.zeros((48, 64, 3), np.uint8)
    for ext in (".png", ".jpg"):
        data = cv2.imencode(ext, img)[1].tobytes()
        assert image_size(data) == (64, 48) and render_payload_problem(data) is None
    png = bytearray(cv2.imencode(".png", img)[1].tobytes())
    png[16:24] = (60000).to_bytes(4, "big") + (60000).to_bytes(4, "big")
    assert "60000x60000" in render_payload_problem(bytes(png))
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    i = next(k for k in range(2, len(jpg) - 1) if jpg[k] == 0xFF and jpg[k + 1] == 0xC0)  # the frame header
    bomb = jpg[:i + 5] + (60000).to_bytes(2, "big") + (60000).to_bytes(2, "big") + jpg[i + 9:]
    assert "60000x60000" in render_payload_problem(bomb)
    assert render_payload_problem("text") == "not bytes" and render_payload_problem(b"GIF89a....") == "not a PNG or JPEG"
    # the header is found however the JPEG is laid out: progressive, or behind an EXIF segment; a cut-off one is refused
    prog = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    exif = prog[:2] + b"\xff\xe1" + (1002).to_bytes(2, "big") + b"E" * 1000 + prog[2:]
    assert image_size(prog) == image_size(exif) == (64, 48) and render_payload_problem(prog[:10]) == "not a PNG or JPEG"

"""The private viser internals the studio touches, in one place (viser 1.1): the upload limits and the
screen every message from a page passes before viser acts on it. (The websocket guard lives in
../webguard.py.)

**Uploads.** viser buffers an upload's parts in memory until the last one arrives, and trusts the size
and the part count the page declares. `limit_uploads` puts two handlers around viser's own:

- at the start (after viser's): refuse a declared size over the limit, a part count other than the
  page's own (ceil(size / 512 KiB)), and more than `MAX_IN_FLIGHT` uploads at once from one tab;
- before each part (ahead of viser's): a part of another size than the page cuts (512 KiB, the last one
  the rest; an empty part was once free to send by the hundred thousand, each held by viser) is refused;
  count the bytes actually received; a transfer that grows past its declared size or the limit, or all
  transfers together (every tab's) past twice the limit, is dropped with its buffered parts before the
  part is stored.

**What a page sends** (`screen_messages`). viser 1.1 takes a page's word for everything: it sets any
property a `GuiUpdateMessage` names (`disabled`, `options`, even its own `update_cb`), casts values
with `type(old)(new)` (a dropdown takes any text, a slider NaN), and stores camera and gizmo reports as
they come. Any page holding the token can send such messages, so every message is checked here, on
the server, before any handler sees it, and dropped when it is not something the real page could send:

- only known message types (the share-URL request, localStorage replies, render replies and forms the
  studio never asks for are dropped);
- a widget update changes only `value`, of a widget that is neither disabled nor hidden (the widget or
  a folder around it), to something that widget allows (`value_problem`: a dropdown or button group
  one of its options, numbers finite and inside the widget's range, text of bounded length, a checkbox
  a boolean, a colour three whole numbers 0..255); the tab is told why, at most once a second;
- camera, click, rectangle and gizmo reports are finite and not degenerate (`scene_problem`: a camera
  whose position is its look-at point, a zero ray, a NaN quaternion); a hidden gizmo's drags are dropped;
- an upload starts only on an upload button that is shown and enabled, and its parts come from the tab
  that started it; a connection that ends takes its unfinished uploads with it (viser forgets those of
  a tab that never reported its camera).

Both of viser's dispatchers are screened: the server's (shared widgets, gizmos, uploads) and each
tab's own (its camera, its clicks, the widgets made for that tab alone, such as a dialog's buttons).
"""

from __future__ import annotations

import itertools
import logging
import math
import reprlib
import time

from apose_studio.geometry.units import MAX_COORDINATE_M
from apose_studio.safeio import unsafe_char

log = logging.getLogger(__name__)

MAX_IN_FLIGHT = 2  # uploads one tab may have under way at once
PAGE_PART_BYTES = 512 * 1024  # the page cuts an upload into parts of this size, the last one the rest (viser 1.1's
# UploadButton.tsx): a start that declares another count, or a part of another size, is not the page's
MAX_TEXT_CHARS = 65_536  # a text field's value (paths are at most 4096)
MAX_MAGNITUDE = 1e12  # a number field without a range of its own
MAX_SCENE_M = 1e6  # coordinates a page may report (camera, rays), metres
MAX_POSE_M = MAX_COORDINATE_M  # a gizmo's position: 10 km, the core's coordinate limit
NOTICE_EVERY_S = 1.0  # a tab is told about refused input at most this often


def scene_serializer(ui):
    """viser's scene serializer (a `.viser` recording, `as_html()` a standalone page) of the scene as `ui` draws
    it now and as it goes on: the server's (`server.get_scene_serializer()`), or one tab's own scene, which
    viser 1.1 has no public call for (the same steps on the tab's connection: register and snapshot under its
    record lock, so that no message lands twice or not at all)."""
    if hasattr(ui, "get_scene_serializer"):
        return ui.get_scene_serializer()
    conn = ui._websock_connection
    buffer = conn.get_message_buffer()
    with conn._record_lock:
        serializer = conn.get_message_serializer(filter=lambda message: message.include_in_scene_serialization)
        with buffer.buffer_lock:
            messages = list(buffer.message_from_id.values())
        for message in messages:
            serializer._insert_message(message)
    return serializer


def limit_uploads(gui, all_states, max_bytes: int, notify) -> bool:
    """Install the limits on `gui` (the server's GUI, or a tab's own); `all_states()` lists the upload buffers
    of every GUI of the studio, counted together. `notify(client_id, title, body, error=True)` tells the
    tab. False (logged) when viser's internals changed and only the after-upload check in the upload
    callback remains."""
    try:
        from viser import _messages  # viser's private message types: may move between viser versions

        states = gui._current_file_upload_states
        handlers = gui._websock_interface._incoming_handlers
    except Exception:
        log.warning("viser's upload internals changed: uploads are size-checked only after they arrive")
        return False

    def refuse(client_id, transfer_uuid: str, why: str) -> None:
        state = states.pop(transfer_uuid, None)
        if state is None:
            return
        state["parts"].clear()
        notify(client_id, "Upload refused", f"{state['filename']}: {why}. Put the file on the server and type its "
               "path instead.", error=True)

    def on_start(client_id, message) -> None:
        if message.transfer_uuid not in states:
            return
        size, parts = int(message.size_bytes), int(message.part_count)
        mine = [t for t, s in states.items() if s["client_id"] == client_id]
        if size > max_bytes:
            refuse(client_id, message.transfer_uuid, f"{size / 2**20:.0f} MB; the limit is {max_bytes / 2**20:.0f} MB")
        elif size < 0 or parts != -(-size // PAGE_PART_BYTES):  # the page's own count: ceil(size / 512 KiB)
            refuse(client_id, message.transfer_uuid, f"declares {parts} parts for {size} bytes; not a file upload")
        elif len(mine) > MAX_IN_FLIGHT:
            refuse(client_id, message.transfer_uuid, f"{len(mine) - 1} uploads are still under way in this tab; "
                   "wait for them to finish")

    def before_part(client_id, message) -> None:
        state = states.get(message.transfer_uuid)
        if state is None or message.part_index in state["parts"]:
            return
        n, last = len(message.content), state["part_count"] - 1
        want = state["total_bytes"] - last * PAGE_PART_BYTES if message.part_index == last else PAGE_PART_BYTES
        if message.part_index <= last and n != want:  # each part as the page cuts it: empty ones too are refused
            refuse(client_id, message.transfer_uuid, f"part {message.part_index} holds {n} bytes; the page sends {want}")
            return
        received = state["transferred_bytes"] + n
        everyone = sum(s["transferred_bytes"] for st in all_states() for s in list(st.values())) + len(message.content)
        if received > state["total_bytes"] or received > max_bytes:
            refuse(client_id, message.transfer_uuid, f"sent {received} bytes but declared {state['total_bytes']}")
        elif everyone > 2 * max_bytes:
            refuse(client_id, message.transfer_uuid, f"uploads under way hold {everyone / 2**20:.0f} MB; the limit "
                   f"is {2 * max_bytes / 2**20:.0f} MB")

    try:
        gui._websock_interface.register_handler(_messages.FileTransferStartUpload, on_start)  # after viser's
        handlers[_messages.FileTransferPart].insert(0, before_part)  # ahead of viser's: refused before stored
    except Exception:
        log.warning("viser's upload internals changed: uploads are size-checked only after they arrive")
        return False
    return True


# --------------------------------------------------------------------------------------- values


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict, _REPR.maxstring, _REPR.maxother = 2, 4, 4, 2, 40, 40


def _short(value) -> str:
    """A value as a message may quote it: its repr, cut short (a 65,536-character text, a list of a
    million numbers) without building the whole of it first."""
    text = _REPR.repr(value)
    return text if len(text) <= 60 else text[:50] + "…"


def _number(v) -> float | None:
    """v as a finite float when it is a number (not a boolean); else None."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)
    except OverflowError:  # an integer beyond any float
        return None
    return f if math.isfinite(f) else None


def _in_range(v, lo, hi, whole: bool, what: str = "") -> str | None:
    f = _number(v)
    if f is None:
        return f"{what}{_short(v)} is not a finite number"
    if whole and f != int(f):
        return f"{what}{_short(v)} is not a whole number"
    if lo is not None and f < lo:
        return f"{what}{f:g} is below its minimum {lo:g}"
    if hi is not None and f > hi:
        return f"{what}{f:g} is above its maximum {hi:g}"
    if abs(f) > MAX_MAGNITUDE:
        return f"{what}{f:g} is beyond ±{MAX_MAGNITUDE:g}"
    return None


def _vector(value, n: int):
    return isinstance(value, (list, tuple)) and len(value) == n


def value_problem(handle, value) -> str | None:
    """Why `value` is not one a page may give this viser widget (None: it is). The rules are the widget's
    own: a dropdown's options, a number's range, a colour's 0..255; a widget kind without rules here
    (a progress bar, an upload button) takes no value from a page at all."""
    import viser

    if isinstance(handle, viser.GuiButtonHandle):
        return None if value is True else f"a button press is true, not {_short(value)}"
    if isinstance(handle, (viser.GuiDropdownHandle, viser.GuiButtonGroupHandle)):
        if not isinstance(value, str) or value not in tuple(handle.options):
            return f"{_short(value)} is not one of its choices"
        return None
    if isinstance(handle, viser.GuiCheckboxHandle):
        return None if isinstance(value, bool) else f"expected true or false, not {_short(value)}"
    if isinstance(handle, viser.GuiTextHandle):
        if not isinstance(value, str):
            return f"expected text, not {_short(value)}"
        if len(value) > MAX_TEXT_CHARS:
            return f"{len(value)} characters; at most {MAX_TEXT_CHARS}"
        bad = "\\x00" if "\x00" in value else unsafe_char(value, "\t\n\r" if handle.multiline else "\t")
        if bad is not None:
            return f"the control or invisible character {bad}; this field takes {'text' if handle.multiline else 'one line of text'} without it"
        return None
    if isinstance(handle, (viser.GuiNumberHandle, viser.GuiSliderHandle)):
        return _in_range(value, handle.min, handle.max, isinstance(handle.value, int) and not isinstance(handle.value, bool))
    if isinstance(handle, viser.GuiMultiSliderHandle):
        current = tuple(handle.value)
        if not _vector(value, len(current)):
            return f"expected {len(current)} numbers, not {_short(value)}"
        whole = all(isinstance(v, int) for v in current)
        problem = next((p for i, v in enumerate(value) if (p := _in_range(v, handle.min, handle.max, whole, f"[{i}] "))), None)
        if problem is None and any(a > b for a, b in zip(value, value[1:])):
            problem = "the handles must be in order"
        return problem
    if isinstance(handle, (viser.GuiVector2Handle, viser.GuiVector3Handle)):
        n = 2 if isinstance(handle, viser.GuiVector2Handle) else 3
        if not _vector(value, n):
            return f"expected {n} numbers, not {_short(value)}"
        lo, hi = handle.min or (None,) * n, handle.max or (None,) * n
        return next((p for i, v in enumerate(value) if (p := _in_range(v, lo[i], hi[i], False, f"[{i}] "))), None)
    if isinstance(handle, (viser.GuiRgbHandle, viser.GuiRgbaHandle)):
        n = 3 if isinstance(handle, viser.GuiRgbHandle) else 4
        if not _vector(value, n):
            return f"expected {n} whole numbers 0..255, not {_short(value)}"
        return next((p for i, v in enumerate(value) if (p := _in_range(v, 0, 255, True, f"[{i}] "))), None)
    return f"a {type(handle).__name__} takes no value from the page"


def _hidden(gui_api, handle) -> bool:
    """The widget, or a folder (tab, tab group) it sits in, is hidden."""
    h = handle
    for _ in range(64):
        if getattr(h, "visible", True) is False:
            return True
        impl = getattr(h, "_impl", None)
        if impl is None:  # a tab: it sits in its tab group
            h = getattr(h, "_parent", None)
        else:
            parent = getattr(impl, "parent_container_id", "root")
            h = None if parent == "root" else gui_api._container_handle_from_uuid.get(parent)
        if h is None:
            return False
    return False


def input_problem(gui_api, handle, updates) -> str | None:
    """Why a page's update of this widget must not be applied (None: apply it)."""
    if not isinstance(updates, dict) or len(updates) != 1 or "value" not in updates:
        keys = [_short(k) for k in itertools.islice(updates, 3)] if isinstance(updates, dict) else [_short(updates)]
        return f"the page may change a widget's value only, not {', '.join(k.strip(chr(39)) for k in keys)}"
    if getattr(handle, "disabled", False):
        return "it is disabled"
    if _hidden(gui_api, handle):
        return "it is hidden"
    return value_problem(handle, updates["value"])


# --------------------------------------------------------------------------------------- scene reports


def _finite_vector(v, n: int, bound: float = MAX_SCENE_M) -> bool:
    return _vector(v, n) and all((f := _number(x)) is not None and abs(f) <= bound for x in v)


def _norm(v) -> float:
    return math.sqrt(sum(float(x) ** 2 for x in v))


def _unit_quaternion(q) -> bool:
    return _finite_vector(q, 4, 2.0) and abs(_norm(q) - 1.0) < 1e-3


def _modifier(m) -> bool:
    return m is None or (isinstance(m, str) and len(m) <= 32)


def scene_problem(message) -> str | None:
    """Why a page's camera, pointer, click, drag or gizmo report is not one a real view can make (None: it
    can): non-finite or absurd numbers, a camera whose position is its look-at point, a zero ray or up."""
    from viser import _messages as m

    if isinstance(message, m.ViewerCameraMessage):
        if not (_unit_quaternion(message.wxyz) and _finite_vector(message.position, 3)
                and _finite_vector(message.look_at, 3) and _finite_vector(message.up_direction, 3, 1e6)):
            return "a camera report with missing or non-finite numbers"
        if math.dist(message.position, message.look_at) < 1e-6:
            return "a camera whose position is its look-at point"
        if _norm(message.up_direction) < 1e-6:
            return "a camera without an up direction"
        fov, near, far = _number(message.fov), _number(message.near), _number(message.far)
        if fov is None or not 0.0 < fov < math.pi or near is None or far is None or not 0.0 <= near < far:
            return "a camera report with an impossible field of view or clipping range"
        sizes = (message.image_width, message.image_height)
        if not all(isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= 100_000 for s in sizes):
            return "a camera report with an impossible image size"
        return None
    if isinstance(message, m.ScenePointerMessage):
        n = {"click": 1, "rect-select": 2}.get(message.event_type if isinstance(message.event_type, str) else "")
        if n is None or not _vector(message.screen_pos, n) or not all(_finite_vector(p, 2, 10.0) for p in message.screen_pos):
            return "a pointer report of no known kind, or with impossible screen positions"
        if n == 1 and not (_finite_vector(message.ray_origin, 3) and _finite_vector(message.ray_direction, 3)
                           and _norm(message.ray_direction) > 1e-9):
            return "a click without a ray"
        return None if _modifier(message.modifier) else "a pointer report with an unknown modifier"
    if isinstance(message, m.SceneNodeClickMessage):
        ok = (isinstance(message.name, str) and _finite_vector(message.ray_origin, 3)
              and _finite_vector(message.ray_direction, 3) and _norm(message.ray_direction) > 1e-9
              and _finite_vector(message.screen_pos, 2, 10.0) and _modifier(message.modifier)
              and (message.instance_index is None or (isinstance(message.instance_index, int)
                                                      and not isinstance(message.instance_index, bool)
                                                      and message.instance_index >= 0)))
        return None if ok else "a click report with missing or non-finite numbers"
    if isinstance(message, m.SceneNodeDragMessage):
        ok = (isinstance(message.name, str) and message.phase in ("start", "update", "end")
              and all(_finite_vector(getattr(message, k), 3) for k in ("start_position", "end_position"))
              and all(_finite_vector(getattr(message, k), 2, 10.0) for k in ("start_screen_pos", "end_screen_pos"))
              and _modifier(message.modifier) and message.button in ("left", "middle", "right"))
        return None if ok else "a drag report with missing or non-finite numbers"
    if isinstance(message, m.TransformControlsUpdateMessage):
        if not (isinstance(message.name, str) and _unit_quaternion(message.wxyz)
                and _finite_vector(message.position, 3, MAX_POSE_M)):
            return "a gizmo pose beyond 10 km, with non-finite numbers, or a rotation that is not a unit quaternion"
        return None
    if isinstance(message, (m.TransformControlsDragStartMessage, m.TransformControlsDragEndMessage)):
        return None if isinstance(message.name, str) else "a gizmo report without a name"
    return None


# --------------------------------------------------------------------------------------- the screen


def _is_str(v, limit: int = 4096) -> bool:
    return isinstance(v, str) and len(v) <= limit


def _is_count(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


MAX_RENDER_SIDE = 8192  # a page's image of its 3D view, as the studio asks for it (a JPEG: within webguard's
# MAX_MESSAGE_BYTES, 1 MiB, where a PNG of a busy view is not)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}  # JPEG start-of-frame markers


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's or JPEG's header, without decoding it; None when it is neither."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        if marker in _SOF:
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
    return None


def render_payload_problem(payload) -> str | None:
    """Why a page's image of its 3D view is refused, or None: only a PNG or JPEG whose header gives at most
    MAX_RENDER_SIDE pixels a side, so that no page can hand the decoder a small file that unpacks to
    gigabytes."""
    if not isinstance(payload, bytes):
        return "not bytes"
    size = image_size(payload)
    if size is None:
        return "not a PNG or JPEG"
    if not (0 < size[0] <= MAX_RENDER_SIDE and 0 < size[1] <= MAX_RENDER_SIDE):
        return f"a {size[0]}x{size[1]} image"
    return None


def screen_messages(server, notify) -> bool:
    """Check every message from a page before viser's handlers run (the rules of the module doc). `notify`
    (client, title, body, error=True) tells the tab that sent refused widget input why. False (logged) when
    viser's internals changed and nothing could be installed."""
    try:
        import viser
        from viser import _messages as m

        ws_server = server._websock_server
        server_dispatch = ws_server._handle_incoming_message
        server.gui._gui_input_handle_from_uuid  # noqa: B018 (fail here, not at the first message)
    except Exception:
        log.error("viser's internals changed: the studio cannot check what pages send; do not expose it")
        return False

    last_notice: dict[int, float] = {}

    def tell(client_id, title: str, why: str) -> None:
        now = time.monotonic()
        if now - last_notice.get(client_id, -1e9) < NOTICE_EVERY_S:
            log.debug("refused input from tab %s (%s): %s", client_id, title, why)
            return
        last_notice[client_id] = now
        log.warning("refused input from tab %s (%s): %s", client_id, title, why)
        client = server.get_clients().get(client_id)
        if client is not None:
            notify(client, title, f"ignored: {why}", error=True)  # the page shows notifications as text, not markup

    simple = {m.CommandTriggerMessage: "uuid", m.TransformControlsDragStartMessage: "name",
              m.TransformControlsDragEndMessage: "name"}
    scene = (m.ViewerCameraMessage, m.ScenePointerMessage, m.SceneNodeClickMessage, m.SceneNodeDragMessage,
             m.TransformControlsUpdateMessage, m.TransformControlsDragStartMessage, m.TransformControlsDragEndMessage)

    def admit(gui_api, scene_api, client_id, message) -> bool:
        kind = type(message)
        if kind is m.GuiUpdateMessage:
            if not _is_str(message.uuid, 256):
                return False
            handle = gui_api._gui_input_handle_from_uuid.get(message.uuid) if gui_api is not None else None
            if handle is None:  # not a widget of this dispatcher's (viser would ignore it)
                return False
            why = input_problem(gui_api, handle, message.updates)
            if why is not None:
                tell(client_id, str(getattr(handle, "label", "") or "Input"), why)
            return why is None
        if kind is m.GuiButtonHoldMessage:
            handle = gui_api._gui_input_handle_from_uuid.get(message.uuid) if gui_api is not None and _is_str(message.uuid, 256) else None
            return (isinstance(handle, viser.GuiButtonHandle) and not handle.disabled and not _hidden(gui_api, handle)
                    and _number(message.frequency) is not None)
        if kind is m.FileTransferStartUpload:
            if not (_is_str(message.source_component_uuid, 256) and _is_str(message.transfer_uuid, 256)
                    and _is_str(message.filename) and _is_str(message.mime_type, 256)
                    and _is_count(message.part_count) and _is_count(message.size_bytes)):
                return False
            handle = gui_api._gui_input_handle_from_uuid.get(message.source_component_uuid) if gui_api is not None else None
            if not isinstance(handle, viser.GuiUploadButtonHandle):
                return False
            if handle.disabled or _hidden(gui_api, handle):
                tell(client_id, str(handle.label), "it is disabled" if handle.disabled else "it is hidden")
                return False
            return True
        if kind is m.FileTransferPart:
            if not (_is_str(message.transfer_uuid, 256) and _is_count(message.part_index)
                    and isinstance(message.content, bytes)
                    and (message.source_component_uuid is None or _is_str(message.source_component_uuid, 256))):
                return False
            state = gui_api._current_file_upload_states.get(message.transfer_uuid) if gui_api is not None else None
            return state is None or state.get("client_id") == client_id  # parts only from the tab that started it
        if kind is m.GetRenderResponseMessage:  # a tab's image of its 3D view, which Download image asks for
            return _is_str(message.render_uuid, 256) and render_payload_problem(message.payload) is None
        if kind in simple:
            if not _is_str(getattr(message, simple[kind]), 4096):
                return False
        if kind in scene:
            why = scene_problem(message)
            if why is not None:
                log.debug("dropped a report from tab %s: %s", client_id, why)
                return False
            if kind is m.TransformControlsUpdateMessage or kind is m.TransformControlsDragStartMessage:
                gizmo = scene_api._handle_from_transform_controls_name.get(message.name) if scene_api is not None else None
                if gizmo is not None and not gizmo.visible:
                    return False  # a hidden gizmo cannot be dragged
            return True
        return kind is m.CommandTriggerMessage  # everything else the studio never asks for

    async def screened_server(client_id, message) -> None:
        try:
            ok = admit(server.gui, server.scene, client_id, message)
        except Exception:  # a message shaped so oddly that checking it failed: not one the page sends
            log.debug("dropped an unreadable message from tab %s", client_id, exc_info=True)
            ok = False
        if ok:
            await server_dispatch(client_id, message)

    def on_connection(conn) -> None:
        own_dispatch = conn._handle_incoming_message

        async def screened_tab(client_id, message) -> None:
            client = server.get_clients().get(client_id)
            try:
                ok = admit(getattr(client, "gui", None), getattr(client, "scene", None), client_id, message)
            except Exception:
                log.debug("dropped an unreadable message from tab %s", client_id, exc_info=True)
                ok = False
            if ok:
                await own_dispatch(client_id, message)

        conn._handle_incoming_message = screened_tab

    def forget(conn) -> None:
        """A connection ended, connected or not: its half-done uploads go (viser drops them only for a tab
        that had reported its camera)."""
        last_notice.pop(conn.client_id, None)
        try:
            server.gui._drop_uploads_from_client(conn.client_id)
        except Exception:
            log.warning("viser's upload internals changed: a closed tab's unfinished uploads may stay buffered")

    try:
        ws_server._handle_incoming_message = screened_server
        ws_server.on_client_connect(on_connection)  # runs before the connection's first message is read
        ws_server.on_client_disconnect(forget)
    except Exception:
        log.error("viser's internals changed: the studio cannot check what pages send; do not expose it")
        return False
    return True

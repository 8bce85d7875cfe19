"""The private viser internals the studio touches, in one place (viser 1.1): the upload limits.
(The websocket guard lives in ../webguard.py.)

viser buffers an upload's parts in memory until the last one arrives, and trusts the size and the
part count the page declares. `limit_uploads` puts two handlers around viser's own:

- at the start (after viser's): refuse a declared size over the limit, a part count that does not fit
  the declared size, and more than `MAX_IN_FLIGHT` uploads at once from one tab;
- before each part (ahead of viser's): count the bytes actually received; a transfer that grows past
  its declared size or the limit, or all transfers together past twice the limit, is dropped with its
  buffered parts before the part is stored.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

MAX_IN_FLIGHT = 2  # uploads one tab may have under way at once


def limit_uploads(server, max_bytes: int, notify) -> bool:
    """Install the limits; False (logged) when viser's internals changed and only the after-upload check
    in the upload callback remains."""
    try:
        from viser import _messages  # viser's private message types: may move between viser versions

        gui = server.gui
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
        client = server.get_clients().get(client_id)
        notify(client, "Upload refused", f"{state['filename']}: {why}. Put the file on the server and type its "
               "path instead.", error=True)

    def on_start(client_id, message) -> None:
        if message.transfer_uuid not in states:
            return
        size, parts = int(message.size_bytes), int(message.part_count)
        mine = [t for t, s in states.items() if s["client_id"] == client_id]
        if size > max_bytes:
            refuse(client_id, message.transfer_uuid, f"{size / 2**20:.0f} MB; the limit is {max_bytes / 2**20:.0f} MB")
        elif size < 0 or parts < 0 or parts > size // 1024 + 1:  # the page sends parts of 512 KiB
            refuse(client_id, message.transfer_uuid, f"declares {parts} parts for {size} bytes; not a file upload")
        elif len(mine) > MAX_IN_FLIGHT:
            refuse(client_id, message.transfer_uuid, f"{len(mine) - 1} uploads are still under way in this tab; "
                   "wait for them to finish")

    def before_part(client_id, message) -> None:
        state = states.get(message.transfer_uuid)
        if state is None or message.part_index in state["parts"]:
            return
        received = state["transferred_bytes"] + len(message.content)
        everyone = sum(s["transferred_bytes"] for s in states.values()) + len(message.content)
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

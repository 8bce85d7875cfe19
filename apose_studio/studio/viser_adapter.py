"""The private viser internals the studio touches, in one place (viser 1.1): the early upload size
check. (The websocket guard lives in ../webguard.py.)"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)


def limit_uploads(server, max_bytes: int, notify) -> None:
    """Refuse an over-size upload when it starts, not after the server has buffered it all."""
    try:
        from viser import _messages

        gui = server.gui

        def check(client_id, message) -> None:
            if message.size_bytes > max_bytes:
                gui._current_file_upload_states.pop(message.transfer_uuid, None)
                client = server.get_clients().get(client_id)
                notify(client, "Upload refused",
                       f"{message.filename} is {message.size_bytes / 2**20:.0f} MB; the limit is "
                       f"{max_bytes / 2**20:.0f} MB. Put the file on the server and type its path instead.", error=True)

        gui._websock_interface.register_handler(_messages.FileTransferStartUpload, check)
    except Exception:  # viser changed its internals: the size is still checked after the upload
        log.info("early upload size check unavailable; checking after upload")

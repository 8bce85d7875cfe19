"""`apose export-html`: the studio's Export replay (HTML) without a browser.

A studio is started on loopback with no page connected, the frame opened and estimated as the Inspect
tab does (its default mask source and settings), and the page its Export replay button would download
is written to a file. The same code draws it as in the studio: what the file shows is what a user
inspecting that frame sees.
"""

from __future__ import annotations

import contextlib
import io
import logging
import socket
from pathlib import Path

from apose_studio.errors import AposeError


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def export_replay(input_path: str | Path, step: int, frame: int, assembly: str | Path | None = None,
                  orientation_prior: bool = False, obj_map: list[str] | None = None) -> tuple[str, object]:
    """(the replay page's HTML, the registration result) for frame `frame` (image id in a dataset or BOP
    scene; 0 for a capture) of `step` in `input_path` (a dataset from `apose render`, or a capture or BOP
    scene folder with `assembly`; `obj_map`: a BOP scene's PART=OBJ_ID items, for its ground truth).
    AposeError when the input cannot be opened, the step or frame does not exist, or the estimate fails."""
    from apose_studio.data.bop import BopScene
    from apose_studio.data.dataset import Dataset
    from apose_studio.data.sources import open_frames
    from apose_studio.studio import serve

    if not isinstance(open_frames(Path(input_path)), Dataset) and assembly is None:  # read here: its errors name it
        raise AposeError(f"{input_path}: a capture or BOP scene has no assembly of its own; give --assembly A.yaml "
                         "(and --step)")
    quiet = logging.getLogger("apose_studio.studio")  # the studio's notices are for a page; the CLI says its own
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    with contextlib.redirect_stdout(io.StringIO()):  # viser says "Server stopped" on stdout if the start fails
        server, st = serve(assembly, input_path, host="127.0.0.1", port=_free_port(), obj_map=obj_map,
                           tabs=False)
    try:
        with st.lock:
            ins = st.inspect
            if ins.frames is None:
                raise AposeError(f"{input_path}: could not be opened as a dataset or capture")
            steps = list(ins.i_step.options)
            chosen = [s for s in steps if s.split(".")[0] == str(step)]
            if not chosen:
                raise AposeError(f"--step {step}: {input_path} has steps {', '.join(s.split('.')[0] for s in steps)}")
            ids = (ins.frames.image_ids(step) if isinstance(ins.frames, Dataset) else
                   ins.frames.image_ids() if isinstance(ins.frames, BopScene) else [0])
            if frame not in ids:
                raise AposeError(f"--frame {frame}: step {step} of {input_path} has frames {', '.join(map(str, ids))}")
            ins._syncing = True
            try:
                ins.i_step.value = chosen[0]
                ins.i_frame.value = ids.index(frame)
                ins.i_prior.value = bool(orientation_prior)
            finally:
                ins._syncing = False
            ins.on_frame_changed()
            ins.run_estimation(False, None)
            result = ins.result
            if result is None or not result.ok:
                raise AposeError(f"the estimate failed: {getattr(result, 'reason', 'no result')}")
            return st.results.replay_html(), result
    finally:
        st.inspect.settle()  # its background preparation must not outlive the process's exit
        quiet.setLevel(level)
        with contextlib.redirect_stdout(io.StringIO()):  # viser says "Server stopped" on stdout
            server.stop()

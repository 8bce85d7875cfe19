"""Shared by the studio tests: a studio on a free port whose notifications are collected, and a click
that goes through `Studio.guarded` as the browser's does (no browser here; tests/e2e drives the real page)."""

import shutil
from pathlib import Path

import pytest

from apose_studio.studio import serve

from ..conftest import SAMPLES, free_port, write_capture


class Click:
    client = None


@pytest.fixture
def studio(monkeypatch, tmp_path):
    made = []

    def start(assembly=None, dataset=None, root=tmp_path):
        server, st = serve(assembly, dataset, host="127.0.0.1", port=free_port(), root=root, tabs=False)
        st.notes = []
        monkeypatch.setattr(st, "notify", lambda client, title, body, error=False, others_of=None, keep=False:
                            st.notes.append((title, body, error)))
        made.append(server)
        return st

    yield start
    for s in made:
        s.stop()


def act(st, fn, *args):
    st.guarded("test")(lambda c: fn(*args, c))(Click())


def errors(st):
    return [n for n in st.notes if n[2]]


@pytest.fixture
def gearbox_copy(tmp_path) -> Path:
    dst = tmp_path / "gearbox"
    shutil.copytree(SAMPLES / "helical_gearbox", dst)
    return dst / "assembly.yaml"


@pytest.fixture
def capture(gearbox_dataset, tmp_path) -> Path:
    """A real-capture folder (rgb.png, depth.png in mm, camera.json) made from a rendered frame."""
    from apose_studio.data.dataset import Dataset

    return write_capture(Dataset(gearbox_dataset).frame(1, 1), tmp_path / "capture")


def open_capture(studio, cap):
    st = studio(SAMPLES / "helical_gearbox" / "assembly.yaml")
    st.inspect.i_path.value = str(cap)
    act(st, lambda c: st.inspect.open_frames(st.inspect.i_path.value, c))
    return st


class Notice:
    """A notification a NoticeTab was shown: its title and body, and whether it was closed."""

    def __init__(self, title: str, body: str):
        self.title, self.body, self.removed = title, body, False

    def remove(self):
        self.removed = True


class NoticeTab:
    """A stand-in for a browser tab (a viser client) that records the notifications it is shown."""

    def __init__(self, client_id: int = 7):
        import types

        self.client_id, self.shown = client_id, []
        self.camera = types.SimpleNamespace()  # (a tab's view, which an action may move)

    def add_notification(self, title, body, **kw):
        self.shown.append(Notice(title, body))
        return self.shown[-1]

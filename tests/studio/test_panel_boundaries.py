"""Panels talk through the app: no panel module reaches another panel through `self.app.<panel>` (the
shared data is `Studio.state`, reactions are `Studio.events`); the hub delivers events in order and
refuses unknown ones; a step selected in the Steps folder shows in the Mates folder."""

import ast
from pathlib import Path

import pytest

from apose_studio.studio import app as app_module
from apose_studio.studio.state import PAYLOAD, Event, Events

from ..conftest import SAMPLES

STUDIO = Path(app_module.__file__).parent
PANEL_MODULES = sorted([*STUDIO.glob("*_panel.py"), STUDIO / "results_view.py"])


def panel_attributes() -> set[str]:
    """The Studio's attributes that hold a panel: `self.<name> = <Class>(self)` in Studio.__init__, with
    <Class> imported from a panel module."""
    tree = ast.parse((STUDIO / "app.py").read_text())
    panel_classes = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                     and (node.module or "").rsplit(".", 1)[-1] in {p.stem for p in PANEL_MODULES} for a in node.names}
    studio = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Studio")
    init = next(n for n in studio.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
    names = set()
    for node in ast.walk(init):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and isinstance(node.value.func, ast.Name)
                and node.value.func.id in panel_classes):
            names |= {t.attr for t in node.targets if isinstance(t, ast.Attribute)}
    return names


def test_the_panel_attributes_are_found():
    assert panel_attributes() == {"files", "steps", "mates", "grasps", "inspect", "prompt", "views", "results", "robot", "sequence"}


@pytest.mark.parametrize("path", PANEL_MODULES, ids=lambda p: p.name)
def test_a_panel_never_reaches_another_panel(path):
    panels = panel_attributes()
    reaches = []
    for node in ast.walk(ast.parse(path.read_text())):
        # self.app.<panel>, however it is used after (an attribute, a call, an alias)
        if (isinstance(node, ast.Attribute) and node.attr in panels and isinstance(node.value, ast.Attribute)
                and node.value.attr == "app" and isinstance(node.value.value, ast.Name) and node.value.value.id == "self"):
            reaches.append(f"line {node.lineno}: self.app.{node.attr}")
        # getattr(self.app, "<panel>")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr" and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant) and node.args[1].value in panels):
            reaches.append(f"line {node.lineno}: getattr(..., {node.args[1].value!r})")
    assert reaches == [], f"{path.name} reaches other panels (use app.state / app.events): {reaches}"


def test_events_reach_their_subscribers_in_order_with_their_payload():
    hub, heard = Events(), []
    hub.on(Event.STEP_SELECTED, lambda index: heard.append(("first", index)))
    hub.on(Event.STEP_SELECTED, lambda index: heard.append(("second", index)))
    hub.on(Event.DRAFT_CHANGED, lambda: heard.append("draft"))
    hub.emit(Event.STEP_SELECTED, index=2)
    assert heard == [("first", 2), ("second", 2)]  # in subscription order; other events' subscribers not called
    hub.emit(Event.DRAFT_CHANGED)
    assert heard[-1] == "draft"
    with pytest.raises(TypeError, match="carries"):
        hub.emit(Event.STEP_SELECTED)  # the payload is fixed per event
    with pytest.raises(TypeError, match="not a studio Event"):
        hub.emit("step selected", index=1)
    with pytest.raises(TypeError, match="not a studio Event"):
        hub.on("anything", print)
    assert set(PAYLOAD) == set(Event)


def test_every_event_has_a_panel_that_listens_and_the_draft_reaches_every_panel(studio):
    st = studio(SAMPLES / "planetary_reducer" / "assembly.yaml")
    assert [e.name for e in Event if not st.events.subscribers(e)] == []
    assert "sun_gear" in st.files.parts_html.content and st.files.f_name.value == st.asm.name  # Assembly panel
    assert "sun_gear" in st.steps.steps_html.content and set(st.state.meshes) == set(st.asm.parts)  # Steps panel
    assert "/assembly/approach" in st.nodes  # Mates panel: the selected step's approach, on the fresh preview


def test_selecting_a_step_shows_its_mates(studio):
    st = studio(SAMPLES / "planetary_reducer" / "assembly.yaml")  # step 1 (the sun gear) has 3 mates, step 2 none
    heard = []
    st.events.on(Event.STEP_SELECTED, lambda index: heard.append(index))
    assert st.state.step_index == 0 and st.mates.list_html.content.count("<tr><td>") == 3
    st.steps.f_step.value = st.steps.f_step.options[1]  # as the browser's dropdown does: through the callback
    assert heard == [1] and st.state.step_index == 1 and st.steps.step_index == 1
    assert "step 2 has no mates" in st.mates.list_html.content and tuple(st.mates.f_mate.options) == ("—",)
    assert int(st.steps.f_upto.value) == 2
    st.steps.f_step.value = st.steps.f_step.options[0]
    assert heard == [1, 0] and st.mates.list_html.content.count("<tr><td>") == 3
    assert tuple(st.mates.f_mate.options) == tuple(f"{j + 1}. {m.type}" for j, m in enumerate(st.asm.steps[0].mates))
    assert [n for n in st.notes if n[2]] == []


def test_panels_start_their_threads_under_the_workspace_s_read_confinement():
    """A thread started with threading.Thread runs outside `safeio.reads_within` (it is per thread): a player
    reading frames there showed an image a link inside the workspace led outside to. Every studio module but
    app.py starts its threads through `Studio.start_thread`, which carries the confinement."""
    starts = []
    for path in STUDIO.glob("*.py"):
        if path.name == "app.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "Thread":
                starts.append(f"{path.name}:{node.lineno}")
    assert starts == []

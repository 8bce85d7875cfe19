"""Notifications are plain text: viser hands a notification's title and body to React as a string, which
shows it as written (no HTML, no markdown), so text escaped for HTML shows its entities ("a cylinder&#x27;s
side" in a not-confident notice). Escaping belongs to markdown and HTML widgets only."""

import ast
from pathlib import Path

STUDIO = Path(__file__).resolve().parents[2] / "apose_studio" / "studio"


def _escaped_notices(tree: ast.AST) -> list[int]:
    """Lines of `notify(...)` / `add_notification(...)` calls and `AposeError(...)` raises (their message becomes a
    notice, app.guarded) whose arguments call `esc`."""
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        if name not in ("notify", "add_notification", "AposeError"):
            continue
        for arg in [*node.args, *(k.value for k in node.keywords)]:
            if any(isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "esc" for n in ast.walk(arg)):
                out.append(node.lineno)
    return out


def test_no_notice_text_is_escaped_for_html():
    found = {p.name: _escaped_notices(ast.parse(p.read_text())) for p in sorted(STUDIO.glob("*.py"))}
    assert not {k: v for k, v in found.items() if v}


def test_the_check_finds_an_escaped_notice():
    code = 'app.notify(c, "t", esc(text))\nraise AposeError(f"{esc(name)} is bad")\napp.notify(c, "t", text)\n'
    assert _escaped_notices(ast.parse(code)) == [1, 2]

"""Who may connect (pure rules; tests/e2e drives them through a real server and browser) and the workspace."""

import pytest

from apose_studio.errors import AposeError
from apose_studio.webguard import Workspace, refusal


def ws(origin, host="127.0.0.1:8080", token=None, path="/", bound_loopback=True):
    return refusal(path=path, host_header=host, origin=origin, port=8080, bound_loopback=bound_loopback,
                   token=token, websocket=True)


def test_origin_must_be_the_studios_own_page():
    assert ws("http://127.0.0.1:8080") is None
    assert ws("http://localhost:8080") is None  # localhost and 127.0.0.1 are one host
    assert ws("http://localhost:8080", host="localhost:8080") is None
    assert ws("http://[::1]:8080", host="[::1]:8080") is None
    for bad in ("http://evil.example.com", "http://127.0.0.1:8081", "http://127.0.0.1", "null", "file://",
                "https://127.0.0.1:9999", None, ""):
        assert ws(bad) is not None, bad
    # DNS rebinding: a foreign name resolving to 127.0.0.1 is same-origin to the browser, but not loopback
    assert "not a loopback name" in ws("http://evil.example.com:8080", host="evil.example.com:8080")


def test_beyond_loopback_the_token_is_needed_and_origin_still_checked():
    kw = dict(host="studio.lan:8080", bound_loopback=False, token="tok")
    assert ws("http://studio.lan:8080", path="/t/tok", **kw) is None
    assert "needs its token" in ws("http://studio.lan:8080", path="/", **kw)
    assert "needs its token" in ws("http://studio.lan:8080", path="/t/wrong", **kw)
    assert "needs its token" in ws("http://studio.lan:8080", path="/t/tokx", **kw)
    assert "not the studio's own page" in ws("http://evil.example.com:8080", path="/t/tok", **kw)
    page = refusal(path="/", host_header="studio.lan:8080", origin=None, port=8080, bound_loopback=False,
                   token="tok", websocket=False)
    assert "needs its token" in page


def test_workspace_confines_paths(tmp_path):
    w = Workspace.of(tmp_path / "a", tmp_path / "b")
    assert w.resolve(tmp_path / "a" / "x.yaml") == (tmp_path / "a" / "x.yaml").resolve()
    assert w.resolve("sub/x.yaml") == (tmp_path / "a" / "sub" / "x.yaml").resolve()  # relative: the first root
    assert w.resolve(tmp_path / "b") == (tmp_path / "b").resolve()
    for outside in ("/etc/passwd", tmp_path / "a" / ".." / "c.yaml", tmp_path / "ab" / "x.yaml", "../../x"):
        with pytest.raises(AposeError, match="outside the studio's workspace"):
            w.resolve(outside)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "link").symlink_to("/etc")
    with pytest.raises(AposeError, match="outside"):  # a link out of the workspace does not count as inside
        w.resolve(tmp_path / "a" / "link" / "passwd")

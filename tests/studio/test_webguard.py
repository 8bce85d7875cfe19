"""Who may connect (pure rules; tests/e2e drives them through a real server and browser), the workspace, and
how much a connection may hold."""

import time

import pytest

from apose_studio.errors import AposeError
from apose_studio.studio.webguard import Workspace, check_token, is_loopback_bind, is_loopback_name, refusal


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


LOOPBACK = ("127.0.0.1", "127.0.0.2", "127.255.255.254", "::1", "[::1]", "localhost", "LOCALHOST", "LocalHost")
NOT_LOOPBACK = ("127.attacker.example", "127.0.0.1.nip.io", "127.0.0.1.rebind.attacker.example", "127", "127.",
                "1270.0.0.1", "127.0.0.1.", "127.1", "0x7f.0.0.1", "0177.0.0.1", "2130706433", "localhost.",
                "localhost.attacker.example", "attacker.localhost", "localhost:80", "::ffff:127.0.0.1",
                "[::ffff:127.0.0.1]", "::2", "0.0.0.0", "::", "", "10.0.0.1", "128.0.0.1", "evil.example")


def test_loopback_names_are_ip_literals_or_exactly_localhost():
    for name in LOOPBACK:
        assert is_loopback_name(name), name
    for name in NOT_LOOPBACK:
        assert not is_loopback_name(name), name
        assert not is_loopback_bind(name), name


def test_names_that_only_look_like_loopback_are_foreign():
    """The probe of round 2: a page from http://127.attacker.example:PORT, and the rebinding forms."""
    for name in NOT_LOOPBACK:
        if not name or ":" in name:
            continue
        assert "not the studio's own page" in ws(f"http://{name}:8080"), name  # Origin only
        assert "not a loopback name" in ws(f"http://{name}:8080", host=f"{name}:8080"), name  # Host too
    for origin in ("http://127.0.0.1:8080@evil.example:8080", "http://evil.example:8080#@127.0.0.1:8080",
                   "http://127.0.0.1%2eevil.example:8080", "http://[::ffff:127.0.0.1]:8080",
                   "ws://127.0.0.1:8080", "chrome-extension://127.0.0.1:8080"):
        assert ws(origin) is not None, origin
    assert ws("http://127.0.0.2:8080") is None  # another loopback address of this machine is this machine
    assert ws("http://[::1]:8080") is None


def test_token_is_compared_whole():
    tok = "a" * 24
    kw = dict(host="127.0.0.1:8080", token=tok)
    for path in (f"/t/{tok}", f"/t/{tok}/", f"/t/{tok}/assets/x.js", f"/t/{tok}?v=1"):
        assert ws("http://127.0.0.1:8080", path=path, **kw) is None, path
    for path in ("/", f"/t/{tok}x", f"/t/{tok[:-1]}", f"/t/{tok[:-1]}/", "/t/", "/t//", f"/x/{tok}/", f"/t/%61{tok[1:]}",
                 f"//t/{tok}/", f"/T/{tok}/", f"/t/{tok.upper()}/"):
        assert "needs its token" in ws("http://127.0.0.1:8080", path=path, **kw), path


def test_chosen_tokens_must_be_unguessable():
    assert check_token("s3cret-token-0123456789") == "s3cret-token-0123456789"
    for bad in ("short", "x" * 15, "has space in it 0123", "slash/in/the/token/0123", "ümlaut-token-0123456789"):
        with pytest.raises(AposeError, match="--token"):
            check_token(bad)


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


def test_rule_edges_pinned_by_mutation_testing():
    from apose_studio.studio.webguard import new_token

    assert is_loopback_bind("127.0.0.1") and is_loopback_bind("localhost") and is_loopback_bind("::1")
    assert not is_loopback_name("[::1") and not is_loopback_name("::1]")  # half a bracket pair is not a literal
    assert not is_loopback_name("x127.0.0.1]") and not is_loopback_name("[127.0.0.1x")  # nor a name wrapped in one
    assert len(new_token()) == 32  # 24 random bytes (192 bits), URL-safe base64
    tok = "b" * 20
    assert ws("http://127.0.0.1:8080", path=f"/t/{tok}/assets/x.js?v=1", token=tok) is None  # '/' before '?'
    assert "needs its token" in ws("http://127.0.0.1:8080", path=f"/t/{tok}?x=/t/{tok}/", token=tok[:-1] + "c")
    # default ports: an Origin without a port means 80 (http) or 443 (https)
    page80 = dict(path="/", host_header="127.0.0.1", port=80, bound_loopback=True, token=None, websocket=True)
    assert refusal(origin="http://127.0.0.1", **page80) is None
    assert refusal(origin="https://127.0.0.1", **page80) is not None
    assert refusal(origin="https://127.0.0.1", **{**page80, "port": 443, "host_header": "127.0.0.1:443"}) is None
    assert refusal(origin="http://127.0.0.1", **{**page80, "port": 81}) is not None
    assert "not a loopback name" in ws("http://127.0.0.1:8080", host="127.0.0.1:99999")  # a bad port: refused, no crash
    a, b = new_token(), new_token()
    assert a != b and len(a) >= 32 and check_token(a) == a  # 24 random bytes
    assert check_token("x" * 16) == "x" * 16  # 16 characters are enough, 15 are not (above)


# ------------------------------------------------------------------ memory and connections (#24 M-e)


def test_a_message_bigger_than_the_page_ever_sends_closes_its_connection_at_once(studio):
    """viser took frames of up to 50 MB: 60 tabs each holding a half-sent 49 MB frame held 4.75 GB. The
    page's biggest message is an upload part of 512 KiB: a frame that declares more is refused from its
    header, before its payload is buffered, and only that connection ends."""
    import websockets

    from .test_page_input import Tab

    st = studio()
    other, tab = Tab(st), Tab(st)
    n = 49 * 2 ** 20
    tab.ws.socket.sendall(bytes([0x82, 0x80 | 127]) + n.to_bytes(8, "big") + b"\0\0\0\0" + b"\0" * 65536)
    t0 = time.time()
    with pytest.raises(websockets.ConnectionClosed) as e:
        while time.time() - t0 < 5:
            tab.ws.recv(timeout=5)  # what the studio sends meanwhile, then its close
    assert e.value.rcvd is not None and e.value.rcvd.code == 1009  # "message too big", sent by the studio
    button = st.files.upload._impl.uuid
    other.send(type="FileTransferStartUpload", source_component_uuid=button, transfer_uuid="t", filename="a.stl",
               mime_type="model/stl", part_count=2, size_bytes=2 ** 20)
    other.send(type="FileTransferPart", source_component_uuid=button, transfer_uuid="t", part_index=0,
               content=b"\0" * 2 ** 19)  # a part as the page sends it still arrives
    other.settle()
    assert st.server.gui._current_file_upload_states["t"]["transferred_bytes"] == 2 ** 19
    other.close()


def test_websockets_at_once_are_capped_with_a_clear_refusal(studio, monkeypatch):
    import websockets

    from apose_studio.studio import webguard

    from .test_page_input import Tab

    monkeypatch.setattr(webguard, "MAX_CONNECTIONS", 3)
    st = studio()
    tabs = [Tab(st) for _ in range(3)]
    with pytest.raises(websockets.InvalidStatus) as e:
        Tab(st)
    assert e.value.response.status_code == 503 and b"3 tabs connected, its limit" in e.value.response.body
    tabs.pop().close()
    for _ in range(50):  # the slot frees once the server has seen the close
        try:
            tabs.append(Tab(st))
            break
        except websockets.InvalidStatus:
            time.sleep(0.05)
    assert len(tabs) == 3
    for t in tabs:
        t.close()


def test_no_websocket_before_the_studio_is_ready():
    """A page that connects while the studio is still being built (its screen of page input not yet in
    place) is asked to come back, and it does by itself."""
    import threading

    import viser
    import websockets.sync.client

    from apose_studio.studio.webguard import start_viser

    from ..conftest import free_port

    ready = threading.Event()
    server = start_viser("127.0.0.1", free_port(), "t" * 24, ready=ready)
    url = f"ws://127.0.0.1:{server.get_port()}/t/{'t' * 24}/"
    kw = dict(origin=f"http://127.0.0.1:{server.get_port()}", subprotocols=[f"viser-v{viser.__version__}"])
    try:
        with pytest.raises(websockets.InvalidStatus) as e:
            websockets.sync.client.connect(url, **kw)
        assert e.value.response.status_code == 503 and b"starting" in e.value.response.body
        ready.set()
        websockets.sync.client.connect(url, **kw).close()
    finally:
        server.stop()


def test_only_origins_and_hosts_as_a_browser_writes_them_pass():
    """#24 second attack: urlsplit read 'http://evil@127.0.0.1:8080' as 127.0.0.1. An Origin is
    scheme://host[:port] and a Host header host[:port]; userinfo, a backslash, whitespace, a path or a
    port with a leading zero is refused before any parsing decides what is loopback."""
    for bad in ("http://evil.example@127.0.0.1:8080", "http://evil.example\\@127.0.0.1:8080", "http://127.0.0.1\t:8080",
                "http://127.0.0.1:8080/x", "http://127.0.0.1:08080", "http://127.0.0.1:8080?", "http://127.0.0.1:8080#",
                "http://127.0.0.1 :8080", "HTTP://127.0.0.1:8080 ", "http:/127.0.0.1:8080", "http://:8080"):
        assert ws(bad) is not None, bad
    for bad_host in ("evil.example@127.0.0.1:8080", "127.0.0.1:8080/x", "127.0.0.1 :8080", "127.0.0.1\\:8080"):
        assert ws("http://127.0.0.1:8080", host=bad_host) is not None, bad_host
    assert ws("http://127.0.0.1:8080", host="127.0.0.1") is None  # a Host without its port (the socket's counts)


def test_every_spelling_of_a_websocket_request_is_checked(studio):
    """'Upgrade: , websocket' (valid for the websockets library, which drops empty list items) skipped the
    Origin check and the connection count; only viser's exact comparison kept it from upgrading."""
    import socket

    st = studio()
    port, token = st.server.get_port(), st.url.rstrip("/").rsplit("/", 1)[-1]
    for upgrade in ("Upgrade: , websocket\r\n", "Upgrade: WebSocket, h2c\r\n", "Upgrade: websocket\r\nUpgrade: x\r\n", ""):
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall((f"GET /t/{token}/ HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: Upgrade\r\n{upgrade}"
                       "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                       "Origin: http://evil.example\r\n\r\n").encode())
            head = s.recv(4096).split(b"\r\n", 1)[0]
        assert b" 403 " in head, (upgrade, head)

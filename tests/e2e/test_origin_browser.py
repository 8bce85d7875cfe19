"""A foreign page in real Chromium cannot drive the studio, even from a host name that starts with
`127.` and resolves to this machine (the probe of safety round 2), and even when it knows the token."""

import http.server
import socketserver
import threading

import pytest

from ..conftest import free_port
from .test_studio_browser import ARGS, CHROMIUM, open_page, wait_until

ATTACK = """<!doctype html><title>attacker</title><script>
window.__ws = "pending";
const ws = new WebSocket(%(url)r, [%(proto)r]);
ws.onopen = () => { window.__ws = "open"; };
ws.onerror = () => { if (window.__ws === "pending") window.__ws = "refused"; };
ws.onclose = () => { if (window.__ws === "pending") window.__ws = "refused"; };
</script>"""


def _serve_page(host: str, port: int, body: str):
    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802
            data = body.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *a):
            pass

    httpd = socketserver.TCPServer((host, port), Page, bind_and_activate=True)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd


def _launch(p, *extra):
    if not CHROMIUM.is_file():
        import os

        reason = "Debian's chromium is not installed (bash scripts/setup.sh installs it)"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)
    return p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS + list(extra))


@pytest.mark.parametrize("name", ["127.attacker.example", "127.0.0.1.nip.io", "localhost.attacker.example"])
def test_page_from_a_127_prefixed_name_cannot_connect(tmp_path, name):
    import viser
    from playwright.sync_api import sync_playwright

    from apose_studio.studio import serve

    token = "known-to-the-attacker-0123"  # the Origin check must hold on its own
    server, st = serve(host="127.0.0.1", port=free_port(), root=tmp_path, token=token)  # st: the desk (tabs of their own)
    port = server.get_port()
    ws_url = f"ws://127.0.0.1:{port}/t/{token}/"
    # the attacker's page: same port, another loopback address, reached by a DNS name mapped onto it
    attack = ATTACK % {"url": ws_url, "proto": f"viser-v{viser.__version__}"}
    httpd = _serve_page("127.0.0.2", port, attack)
    try:
        with sync_playwright() as p:
            browser = _launch(p, f"--host-resolver-rules=MAP {name} 127.0.0.2")
            try:
                page = browser.new_page()
                page.goto(f"http://{name}:{port}/")
                assert page.evaluate("location.host") == f"{name}:{port}"
                wait_until(lambda: page.evaluate("window.__ws") != "pending", "the attacker's websocket", 20)
                assert page.evaluate("window.__ws") == "refused"
                assert not server.get_clients()
                # control: the same script on the studio's own page does connect (the probe can see an open)
                own = open_page(browser, st)
                own.evaluate(attack.split("<script>")[1].split("</script>")[0])
                wait_until(lambda: own.evaluate("window.__ws") != "pending", "the studio page's websocket", 20)
                assert own.evaluate("window.__ws") == "open"
            finally:
                browser.close()
    finally:
        httpd.shutdown()
        httpd.server_close()
        server.stop()

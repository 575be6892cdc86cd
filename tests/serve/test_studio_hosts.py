"""The studio by the name the server was given, and a page of another site, in a real browser
(test_studio_page.py says how): the studio works through the allowed name, a name rebound to
127.0.0.1 gets only 400s, and another site's page can send the server nothing it reads."""

import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from tests.support.serving import Client
from tests.support.studio_page import VIEWPORT, Studio, draw

ATTACK_PAGE = b"""<!doctype html><meta charset="utf-8"><title>another site</title>
<p>a page of another site</p>"""


@pytest.fixture
def named_browser(browser: Any) -> Iterator[Any]:
    """A Chromium that resolves the allowed name (serve_app.ALLOWED_HOST) and attacker.test to
    127.0.0.1, as DNS would for a server's own name and for a name rebound to loopback;
    launched by the module's own Playwright (one Playwright runs in a process at a time)."""
    from tests.support.serve_app import ALLOWED_HOST
    from tests.support.studio_page import CHROMIUM, CHROMIUM_ARGS

    rules = f"--host-resolver-rules=MAP {ALLOWED_HOST} 127.0.0.1, MAP attacker.test 127.0.0.1"
    chromium = browser.browser_type.launch(executable_path=CHROMIUM, args=[*CHROMIUM_ARGS, rules])
    try:
        yield chromium
    finally:
        chromium.close()


@pytest.fixture
def attack_site() -> Iterator[int]:
    """A plain HTTP server on a port of its own serving ATTACK_PAGE: another site's page."""
    import http.server
    import threading

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.end_headers()
            self.wfile.write(ATTACK_PAGE)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()


def test_the_studio_works_by_its_name_and_no_other_site_can_use_the_server(
    named_browser: Any, client: Client, attack_site: int
) -> None:
    """Opened through the name the server was given, the studio draws and retrieves as
    through 127.0.0.1. A name rebound to 127.0.0.1 gets only 400s. A page of another site can
    send the server no drawing: its posts that need no preflight (of no type, or plain text)
    are refused 415 unread, and a JSON post is stopped by the browser's preflight, which the
    server does not grant."""
    from tests.support.serve_app import ALLOWED_HOST

    context = named_browser.new_context(viewport=VIEWPORT)
    try:
        page = context.new_page()
        page.set_default_timeout(30_000)
        studio = Studio(page, f"http://{ALLOWED_HOST}:{client.port}")
        studio.open()
        t = np.linspace(0, 2 * np.pi, 60)
        draw(studio, np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(t)], 1).tolist())
        studio.click("retrieve-button")
        page.get_by_test_id("result").nth(2).wait_for()
        assert studio.unexpected_errors() == []

        # DNS rebinding: the attacker's own name, now pointing at this machine.
        rebound = page.goto(f"http://attacker.test:{client.port}/")
        assert rebound is not None and rebound.status == 400
        assert "Host 'attacker.test" in json.loads(rebound.body())["error"]

        # Another site's page posting to the server's address.
        page.goto(f"http://attacker.test:{attack_site}/")
        answers: dict[str, int] = {}
        page.on("response", lambda r: answers.__setitem__(f"{r.request.method} {r.url}", r.status))
        target = f"http://127.0.0.1:{client.port}/api/curve"
        drawing = json.dumps({"name": "a.csv", "text": "0,0\n1,1\n2,0\n"})
        outcomes = page.evaluate(
            """async ([target, body]) => {
                // A Blob of no type is sent with no Content-Type at all.
                const untyped = new Blob([body]);
                await fetch(target + "?untyped", {method: "POST", mode: "no-cors", body: untyped});
                const plain = await fetch(target, {method: "POST", mode: "no-cors", body});
                let json = "sent";
                try {
                    await fetch(target, {
                        method: "POST", body, headers: {"Content-Type": "application/json"}});
                } catch (err) { json = "refused by the browser"; }
                return {plain: plain.type, json};
            }""",
            [target, drawing],
        )
        assert outcomes == {"plain": "opaque", "json": "refused by the browser"}, outcomes
        page.wait_for_timeout(500)
        assert answers.get(f"POST {target}") == 415, answers
        assert answers.get(f"POST {target}?untyped") == 415, answers
        assert answers.get(f"OPTIONS {target}") not in (200, 204), answers
    finally:
        context.close()

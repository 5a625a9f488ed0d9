"""Issue 26: a viewer bound to an address other machines reach needs its token in the URL.

`--host 0.0.0.0` gave no access control to a server that hands out the session's photos and starts
reconstructions.  Now a non-loopback host prints a warning and every request (the page, its assets,
the websocket) must carry the viewer's token: ``?token=`` in the URL, then the cookie the first
answer sets.  Tested with an HTTP client, a websocket client, the CLI (view and capture --view) and
a real browser (Debian chromium via Playwright).  The servers bind 0.0.0.0 and are reached over
127.0.0.1.
"""

import os
import re
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"
CHROMIUM = "/usr/bin/chromium"


def _get(url, cookie=None):
    """(status, headers, body) of a GET."""
    req = urllib.request.Request(url, headers={"Cookie": cookie} if cookie else {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


def _ws(port, cookie=None, query=""):
    """True when a viser websocket handshake succeeds."""
    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    try:
        with connect(f"ws://127.0.0.1:{port}/{query}", subprotocols=[f"viser-v{viser.__version__}"],
                     additional_headers={"Cookie": cookie} if cookie else None, open_timeout=10):
            return True
    except InvalidStatus as e:
        assert e.response.status_code == 403
        return False


@pytest.fixture(scope="module")
def exposed():
    from organlab.viewer import LiveView

    v = LiveView(host="0.0.0.0", port=0)
    yield v
    v.stop()


def test_a_request_without_the_token_is_refused_and_with_it_works(exposed):
    port, token = exposed.port, exposed.token
    assert token and len(token) >= 20 and exposed.url.endswith(f":{port}/?token={token}")
    base = f"http://127.0.0.1:{port}/"
    for url in (base, base + "index.html", base + "?token=", base + "?token=" + token[:-1] + "x"):
        status, _, body = _get(url)
        assert status == 403 and b"token" in body and b"<html" not in body, url
    status, headers, body = _get(base + f"?token={token}")
    assert status == 200 and b"<html" in body[:200].lower()
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(f"organlab_token={token};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    # the page's own requests and its websocket carry the cookie
    assert _get(base + "index.html", cookie=f"organlab_token={token}")[0] == 200
    assert _get(base, cookie="organlab_token=wrong")[0] == 403
    assert not _ws(port) and not _ws(port, cookie="organlab_token=wrong")
    assert _ws(port, cookie=f"organlab_token={token}") and _ws(port, query=f"?token={token}")


def test_loopback_needs_no_token_and_tokens_differ():
    from organlab.viewer import LiveView, is_loopback

    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.1")
    with LiveView(port=0) as local, LiveView(host="0.0.0.0", port=0) as a, LiveView(host="0.0.0.0", port=0) as b:
        assert local.token is None and _get(local.url)[0] == 200 and "token" not in local.url
        assert a.token != b.token  # random per server
        assert _get(f"http://127.0.0.1:{a.port}/?token={b.token}")[0] == 403


def _url_from(proc, timeout=120):
    """The viewer's URL printed by a CLI process (stdout), and its stderr lines so far."""
    t0 = time.monotonic()
    for line in proc.stdout:
        m = re.search(r"(http://\S+)", line)
        if m:
            return m.group(1)
        assert time.monotonic() - t0 < timeout
    raise AssertionError(proc.stderr.read())


@pytest.mark.slow
@pytest.mark.parametrize("args", [
    ["view", str(SAMPLE), "--voxel-size", "4"],
    ["capture", "--turntable", "sim", "--camera", "sim", "--step", "90", "--sim-size", "320x240", "--quiet", "--view",
     "--out", "OUT"],
], ids=["view", "capture"])
def test_cli_with_a_non_loopback_host_warns_and_requires_the_token(args, tmp_path):
    args = [str(tmp_path / "cap") if a == "OUT" else a for a in args]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "organlab", *args, "--host", "0.0.0.0", "--port", "0"], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    try:
        url = _url_from(p)
        m = re.fullmatch(r"http://127\.0\.0\.1:(\d+)/\?token=([\w-]+)", url)
        assert m, url
        port = m.group(1)
        assert _get(f"http://127.0.0.1:{port}/")[0] == 403
        assert _get(url)[0] == 200
    finally:
        p.kill()  # the process this test started
        _, err = p.communicate(timeout=30)
    assert "warning: --host 0.0.0.0 is not this machine only" in err and "without the token are refused" in err


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"{CHROMIUM} missing: 'make test' installs Debian's chromium")
def test_browser_without_the_token_gets_nothing_and_with_it_the_viewer_connects(exposed):
    from playwright.sync_api import sync_playwright

    args = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox", "--no-first-run"]
    before = len(exposed.server.get_clients())
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=args, headless=True)
        try:
            page = browser.new_page()
            r = page.goto(f"http://127.0.0.1:{exposed.port}/")
            assert r.status == 403 and "needs its link with the token" in page.content()
            page.wait_for_timeout(1000)
            assert len(exposed.server.get_clients()) == before  # no websocket either
            r = page.goto(f"http://127.0.0.1:{exposed.port}/?token={exposed.token}")
            assert r.status == 200
            t0 = time.monotonic()  # the page's websocket, with the cookie, is a connected viser client
            while len(exposed.server.get_clients()) == before and time.monotonic() - t0 < 30:
                page.wait_for_timeout(200)
            assert len(exposed.server.get_clients()) == before + 1
            page.reload()  # without the token in the URL, the cookie alone lets it in again
            assert page.goto(f"http://127.0.0.1:{exposed.port}/").status == 200
        finally:
            browser.close()

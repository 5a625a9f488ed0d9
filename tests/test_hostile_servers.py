"""Issue 26, item 3: a server that cannot start ends in one line at once (it hung for ever).

Every case runs in a subprocess with a timeout, so a regression fails instead of hanging the suite.
"""

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"


def _run(args, timeout=60):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "organlab", *args], capture_output=True, text=True, timeout=timeout,
                          env=env, stdin=subprocess.DEVNULL)


def _one_line(p, *needles):
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert all(n in lines[0] for n in needles), lines[0]


@pytest.mark.parametrize("args", [
    ["view", str(SAMPLE), "--port", "99999"],
    ["capture", "--turntable", "sim", "--out", "UNUSED", "--view", "--port", "99999"],
    ["view", str(SAMPLE), "--port", "-1"],
    ["view", str(SAMPLE), "--port", "http"],
])
def test_bad_port_is_one_line_before_anything_starts(args, tmp_path):
    args = [str(tmp_path / "cap") if a == "UNUSED" else a for a in args]
    _one_line(_run(args, timeout=30), "--port")
    assert not (tmp_path / "cap").exists()  # refused before the capture began


def test_port_in_use_is_refused_at_once():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        _one_line(_run(["view", str(SAMPLE), "--port", str(port)], timeout=30), f"--port {port}", "already in use")


def test_host_that_is_not_this_machine_is_one_line():
    # 192.0.2.1 is TEST-NET-1 (RFC 5737): never an address of this machine
    _one_line(_run(["view", str(SAMPLE), "--host", "192.0.2.1", "--port", "0"], timeout=30), "192.0.2.1")


def test_server_thread_failure_reaches_the_main_thread():
    """A start whose server thread dies while the main thread waits for it (what viser did)."""
    code = (
        "import threading\n"
        "from organlab.cli import _start_server\n"
        "from organlab.errors import OrganlabError\n"
        "def start():\n"
        "    ready = threading.Semaphore(0)\n"
        "    threading.Thread(target=lambda: (_ for _ in ()).throw(OverflowError('bind(): port must be 0-65535.')), daemon=True).start()\n"
        "    ready.acquire()\n"  # never released: the old hang
        "try:\n"
        "    _start_server(start, 'organlab view')\n"
        "except OrganlabError as e:\n"
        "    print('ERROR', e)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert p.returncode == 0 and "ERROR organlab view: the server could not start (OverflowError" in p.stdout, p.stdout + p.stderr
    assert "Traceback" not in p.stderr


def test_sim_size_zero_is_one_line(tmp_path):
    _one_line(_run(["capture", "--turntable", "sim", "--out", str(tmp_path / "c"), "--sim-size", "0x0", "--quiet"]),
              "--sim-size")


def test_non_loopback_host_is_warned_about():
    from organlab.cli import _loopback

    assert _loopback("127.0.0.1") and _loopback("localhost") and _loopback("::1")
    assert not _loopback("0.0.0.0") and not _loopback("192.0.2.1")

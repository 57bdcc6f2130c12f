"""report.html: its content, and a real headless Chromium loading it with no console errors and every figure
decoded (driven over the DevTools protocol with a small stdlib websocket client). Needs Debian's
`chromium` package; skipped with a message without it."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import time
import urllib.request
from pathlib import Path
from urllib.parse import urlparse

import pytest

from saft.export import report_command
from saft.export.report import write_report

SECTIONS = ["summary", "losses", "metrics", "params", "maps", "renders", "depth", "timings", "config"]


@pytest.fixture(scope="module")
def full_report(shared_result_dir) -> Path:
    """One report of a result with every optional part, shared by the content and browser checks."""
    out = report_command(shared_result_dir)
    assert out == shared_result_dir / "report.html"
    return out


def test_report_content(full_report):
    text = full_report.read_text()
    for sid in SECTIONS:
        assert f'<section id="{sid}">' in text
    assert '<p class="none">' not in text  # every section has its data in this result
    # self-contained: no external resources of any kind
    assert not re.search(r'(src|href)="(?!data:|#)', text)
    assert "http://" not in text and "https://" not in text
    assert text.count('<img src="data:image/png;base64,') == 14
    assert "wave &lt;test&gt; &amp; co" in text  # config shown, HTML-escaped
    assert "constant_acceleration" in text and "substeps" in text
    assert "12.25 s" in text
    assert "cd2_1e-4m2 (1e-4 m^2)" in text and "num_gt_points" not in text  # units shown, counts not plotted


def test_metrics_series_formats():
    from saft.export.figures import metrics_series

    records = {"per_frame": [{"frame": 2, "CD2": 1.0, "note": "x"}, {"frame": 3, "CD2": 2.0}], "mean": {"CD2": 1.5}}
    series, means = metrics_series(records)
    assert list(series) == ["CD2"] and series["CD2"][0].tolist() == [2.0, 3.0] and means == {"CD2": 1.5}
    lists = {"per_frame": {"cd1_cm": [1.0, float("nan"), 3.0]}, "units": {"cd1_cm": "cm"}}
    series, means = metrics_series(lists)
    assert series["cd1_cm (cm)"][0].tolist() == [0.0, 2.0] and means == {}


def test_report_without_optional_parts(bare_result_dir, tmp_path):
    out = write_report(bare_result_dir, tmp_path / "sub" / "r.html")
    text = out.read_text()
    assert "no metrics.json" in text and "no depth ground truth" in text
    assert "material/" not in text.split('id="maps"')[1].split("</section>")[0]
    assert text.count("<img ") == 5  # 2 loss phases, texture, contact sheet, timings


def test_report_minimal_result(bare_result_dir, tmp_path):
    for name in ("log.csv", "timings.json", "config.toml", "texture.png"):
        (bare_result_dir / name).unlink()
    shutil.rmtree(bare_result_dir / "renders")
    text = write_report(bare_result_dir).read_text()
    for msg in ("no log.csv", "no timings.json", "no config.toml", "no renders/", "no texture.png"):
        assert msg in text


# ---------------------------------------------------------------------------- headless Chromium
def _chromium() -> str | None:
    for name in (os.environ.get("SAFT_CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


class _WebSocket:
    """Just enough of RFC 6455 for the DevTools protocol: text frames, client masking, fragments, ping."""

    def __init__(self, url: str, timeout: float = 30.0):
        u = urlparse(url)
        self.sock = socket.create_connection((u.hostname, u.port), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET {u.path} HTTP/1.1\r\nHost: {u.hostname}:{u.port}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n")
                          .encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("websocket handshake: connection closed")
            head += chunk
        head, self.buf = head.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            raise ConnectionError(f"websocket handshake refused: {head[:200]!r}")

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 16)
            if not chunk:
                raise ConnectionError("websocket closed")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def _send_frame(self, opcode: int, payload: bytes) -> None:
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        masked = (int.from_bytes(payload, "big") ^ int.from_bytes((mask * (n // 4 + 1))[:n], "big")).to_bytes(n, "big")
        self.sock.sendall(head + mask + masked)

    def send(self, text: str) -> None:
        self._send_frame(0x1, text.encode())

    def recv(self) -> str:
        parts = []
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else None
            data = self._read(n)
            if mask:
                data = bytes(c ^ mask[i % 4] for i, c in enumerate(data))
            opcode = b0 & 0x0F
            if opcode == 0x8:
                raise ConnectionError("websocket closed by the browser")
            if opcode == 0x9:
                self._send_frame(0xA, data)
                continue
            if opcode in (0x1, 0x2, 0x0):
                parts.append(data)
                if b0 & 0x80:
                    return b"".join(parts).decode()

    def close(self) -> None:
        try:
            self._send_frame(0x8, b"")
        except OSError:
            pass
        self.sock.close()


class _Browser:
    """Headless Chromium with one page, driven over the DevTools protocol."""

    def __init__(self, exe: str, workdir: Path):
        profile = workdir / "chromium-profile"
        profile.mkdir(parents=True)
        self.log = open(workdir / "chromium-stderr.txt", "wb")
        self.proc = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-dev-shm-usage", f"--user-data-dir={profile}", "--remote-debugging-port=0",
             "--window-size=1200,900", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=self.log)
        port_file = profile / "DevToolsActivePort"
        deadline = time.time() + 30
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.time() > deadline:
                self.close()
                raise RuntimeError(f"chromium did not start: {(workdir / 'chromium-stderr.txt').read_text()[-2000:]}")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        while True:
            pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
            pages = [p for p in pages if p.get("type") == "page"]
            if pages or time.time() > deadline:
                break
            time.sleep(0.1)
        self.ws = _WebSocket(pages[0]["webSocketDebuggerUrl"])
        self.next_id = 0
        self.events: list[dict] = []
        for method in ("Runtime.enable", "Log.enable", "Page.enable"):
            self.call(method)

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        my_id = self.next_id
        self.ws.send(json.dumps({"id": my_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == my_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self.events.append(msg)

    def wait_event(self, method: str, timeout: float = 30.0) -> dict:
        deadline = time.time() + timeout
        while time.time() < deadline:
            for i, ev in enumerate(self.events):
                if ev["method"] == method:
                    return self.events.pop(i)
            msg = json.loads(self.ws.recv())
            if "method" in msg:
                self.events.append(msg)
        raise TimeoutError(method)

    def open(self, path: Path) -> tuple[dict, list[str]]:
        """Load a file; return what the page reports about itself and every console/JS/resource error."""
        self.events.clear()
        self.call("Page.navigate", url=path.resolve().as_uri())
        self.wait_event("Page.loadEventFired")
        probe = ("Promise.all(Array.from(document.images).map(i => i.decode().catch(() => null))).then(() => "
                 "JSON.stringify({title: document.title, "
                 "images: Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.naturalHeight]), "
                 "figures: document.querySelectorAll('figure img').length, "
                 "sections: Array.from(document.querySelectorAll('section')).map(s => s.id)}))")
        res = self.call("Runtime.evaluate", expression=probe, awaitPromise=True, returnByValue=True)
        info = json.loads(res["result"]["value"])
        self.call("Runtime.evaluate", expression="0")  # flush events queued behind the probe
        errors = []
        for ev in self.events:
            p = ev.get("params", {})
            if ev["method"] == "Runtime.exceptionThrown":
                errors.append("exception: " + json.dumps(p.get("exceptionDetails", {}))[:300])
            elif ev["method"] == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append("console.error: " + json.dumps(p.get("args", []))[:300])
            elif ev["method"] == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                errors.append("log: " + p["entry"].get("text", "")[:300])
        return info, errors

    def close(self) -> None:
        try:
            if hasattr(self, "ws"):
                self.call("Browser.close")
                self.ws.close()
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    exe = _chromium()
    if exe is None:
        pytest.skip("chromium not installed (Debian: apt-get install -y chromium): the headless-browser check "
                    "of report.html is skipped")
    b = _Browser(exe, tmp_path_factory.mktemp("chromium"))
    yield b
    b.close()


def test_report_in_headless_chromium(browser, full_report):
    info, errors = browser.open(full_report)
    assert errors == []
    assert info["title"].startswith("saft report")
    assert info["sections"] == SECTIONS
    assert info["figures"] == len(info["images"]) == 14
    bad = [i for i, (complete, w, h) in enumerate(info["images"]) if not (complete and w > 0 and h > 0)]
    assert bad == [], f"images that did not decode: {bad}"


def test_browser_check_sees_errors(browser, tmp_path):
    """The harness itself: a page with a broken image and a console error is caught."""
    page = tmp_path / "broken.html"
    page.write_text('<!DOCTYPE html><html><head><link rel="icon" href="data:,"></head><body>'
                    '<img src="data:image/png;base64,AAAA"><script>console.error("boom")</script></body></html>')
    info, errors = browser.open(page)
    assert any("boom" in e for e in errors)
    assert info["images"][0][1] == 0

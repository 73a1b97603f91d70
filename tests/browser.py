"""Headless Chromium (Debian's ``chromium``) driven over the DevTools protocol, for tests that
check what a reader of a report sees: the page laid out at a given window size, its scripts
run, its images decoded. ``Page(path).eval(js)`` returns the value of a JavaScript expression.
Tests using it are integration tests; they skip with the reason when chromium is absent."""

from __future__ import annotations

import contextlib
import itertools
import json
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("headless Chromium not installed (Debian: apt-get install chromium)")
    return exe


class Page:
    """``path`` (an HTML file) open in a headless Chromium window of ``width`` x ``height``
    CSS pixels, loaded (the load event fired). Close with ``close()`` or as a context manager."""

    def __init__(self, path: Path, width: int = 1400, height: int = 900,
                 timeout: float = 60.0) -> None:
        from websockets.sync.client import connect

        # Chromium's helper processes may still write to the profile as it exits
        self._profile = tempfile.TemporaryDirectory(prefix="ddfuse-chromium-",
                                                    ignore_cleanup_errors=True)
        self._proc = subprocess.Popen(
            [chromium(), "--headless=new", "--no-sandbox", "--disable-gpu",
             "--no-first-run", "--remote-debugging-port=0", "--remote-allow-origins=*",
             f"--user-data-dir={self._profile.name}", f"--window-size={width},{height}",
             "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self._ids = itertools.count(1)
        self._stack = contextlib.ExitStack()
        try:
            port = self._devtools_port(timeout)
            end = time.monotonic() + timeout
            while True:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
                if pages:
                    break
                assert time.monotonic() < end, "chromium opened no page"
                time.sleep(0.1)
            self._ws = self._stack.enter_context(
                connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout))
            self._timeout = timeout
            self.call("Page.enable")
            self.call("Page.navigate", url=Path(path).resolve().as_uri())
            self._wait_event("Page.loadEventFired")
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout: float) -> int:
        end = time.monotonic() + timeout
        for line in self._proc.stderr:
            m = re.search(r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", line)
            if m:
                return int(m.group(1))
            assert time.monotonic() < end, "chromium did not start its DevTools server"
        raise AssertionError(f"chromium exited ({self._proc.wait()}) before its DevTools server")

    def _recv(self) -> dict:
        return json.loads(self._ws.recv(timeout=self._timeout))

    def _wait_event(self, method: str) -> dict:
        while True:
            msg = self._recv()
            if msg.get("method") == method:
                return msg

    def call(self, method: str, **params) -> dict:
        i = next(self._ids)
        self._ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = self._recv()
            if msg.get("id") == i:
                assert "error" not in msg, f"{method}: {msg['error']}"
                return msg["result"]

    def eval(self, expression: str):
        """The value of a JavaScript ``expression`` in the page (JSON-serialisable)."""
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                      awaitPromise=True)
        assert "exceptionDetails" not in r, f"{expression}: {r['exceptionDetails']}"
        return r["result"].get("value")

    def close(self) -> None:
        self._stack.close()
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._proc.stderr.close()
        self._profile.cleanup()

    def __enter__(self) -> Page:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""A small Chrome DevTools Protocol client: starts Debian's chromium headless and drives pages over CDP.

Only what the browser tests need: targets (tabs), Runtime.evaluate, Input.dispatchMouseEvent,
Page.captureScreenshot. Transport: python3-websocket (Debian package)."""
import base64
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request

import websocket  # python3-websocket

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-default-apps", "--disable-extensions", "--mute-audio",
    # WebGL without a GPU: SwiftShader through ANGLE (NGL needs WebGL)
    "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--remote-allow-origins=*", "--window-size=900,650",
]


def find_chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    raise RuntimeError("chromium not found: apt-get install chromium (scripts/install_deps.sh does)")


class Page:
    def __init__(self, ws_url):
        self.ws = websocket.create_connection(ws_url, timeout=60, suppress_origin=True)
        self.next_id = 0

    def call(self, method, **params):
        self.next_id += 1
        mid = self.next_id
        self.ws.send(json.dumps({"id": mid, "method": method, "params": params}))
        while True:
            m = json.loads(self.ws.recv())
            if m.get("id") == mid:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})

    def eval(self, expr):
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"page exception in {expr!r}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def mouse(self, kind, x, y, buttons=0, button="none"):
        self.call("Input.dispatchMouseEvent", type=kind, x=float(x), y=float(y), button=button,
                  buttons=buttons, clickCount=1 if kind in ("mousePressed", "mouseReleased") else 0)

    def screenshot(self, path):
        data = self.call("Page.captureScreenshot", format="png")["data"]
        with open(path, "wb") as f:
            f.write(base64.b64decode(data))

    def close(self):
        try:
            self.ws.close()
        except Exception:
            pass


class Browser:
    def __init__(self, extra_flags=()):
        self.profile = tempfile.mkdtemp(prefix="haptree_chromium_")
        args = [find_chromium(), *CHROMIUM_FLAGS, *extra_flags, f"--user-data-dir={self.profile}",
                "--remote-debugging-port=0", "about:blank"]
        self.log_path = os.path.join(self.profile, "chromium.log")
        self.log = open(self.log_path, "w+")
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.time() + 60
        self.port = None
        while time.time() < deadline and self.port is None:
            time.sleep(0.2)
            with open(self.log_path) as f:
                m = re.search(r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", f.read())
            if m:
                self.port = int(m.group(1))
            if self.proc.poll() is not None:
                break
        if self.port is None:
            with open(self.log_path) as f:
                raise RuntimeError("chromium did not start; its output:\n" + f.read()[-3000:])

    def _json(self, path, method="GET"):
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", method=method)
        with urllib.request.urlopen(req, timeout=30) as r:
            return json.loads(r.read())

    def new_page(self, url):
        t = self._json("/json/new?" + url, method="PUT")
        p = Page(t["webSocketDebuggerUrl"])
        p.target_id = t["id"]
        p.call("Page.enable")
        return p

    def close_page(self, page):
        page.close()
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/json/close/{page.target_id}")
        with urllib.request.urlopen(req, timeout=30) as r:   # answers "Target is closing", not JSON
            r.read()

    def quit(self):
        try:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        except Exception:
            self.proc.kill()
        self.log.close()
        shutil.rmtree(self.profile, ignore_errors=True)

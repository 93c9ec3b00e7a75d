"""Access control of the viewer (CTest label `browser`): tokens, roles, Origin, TLS, every refusal counted.

  viewer_access_test.py VIEWER OUT_DIR

Runs the stand-alone viewer on memq:// (no session needed: it serves the scene's initial pose) and checks
  * HTTP: no token, a wrong token (query or cookie) -> 403; the token -> 200 and an HttpOnly cookie with
    which the page's other files load; a wrong path with the token -> 404;
  * WebSocket: no token, a wrong token, a foreign Origin -> 403; the pull token -> user 0 (role pull); the
    cookie alone -> accepted; the watch token -> role watch, no user, and its press is refused;
  * every refusal counted (the viewer's summary at exit) and logged once per client and reason;
  * --viewer-no-token with a bind off the loopback, a short token file: refused at start with a one-line error;
  * TLS with a self-signed certificate made here by openssl: `openssl s_client` handshakes (certificate
    verified against itself) and gets 200 with the token, 403 without; Chromium
    (--ignore-certificate-errors) loads the page over https, opens wss, gets frames, and after a reload
    without the token in the URL (the cookie) loads it again; without token it sees the refusal.
Exit 0 on success; prints what failed otherwise."""
import json
import os
import re
import signal
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request

import websocket  # python3-websocket

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "browser"))
import cdp  # noqa: E402

failures = []


def check(cond, what):
    print(("ok   " if cond else "FAIL ") + what, flush=True)
    if not cond:
        failures.append(what)


class ViewerProc:
    def __init__(self, exe, args, log_path):
        self.log = open(log_path, "w")
        self.proc = subprocess.Popen([exe, "--lcm-url", "memq://", "--scene", "chain", "--n", "5", "--viewer-port", "0",
                                      "--viewer-users", "1", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines = []
        self.url = None
        t_end = time.time() + 30
        for line in self.proc.stdout:
            self.log.write(line)
            self.lines.append(line)
            m = re.match(r"viewer: open (\S+)", line)
            if m:
                self.url = m.group(1)
                break
            if time.time() > t_end:
                break
        assert self.url, "the viewer printed no URL:\n" + "".join(self.lines[-10:])
        m = re.match(r"(https?)://([\d.]+):(\d+)/\?token=(\S+)$", self.url)
        assert m, self.url
        self.scheme, self.host, self.port, self.token = m.group(1), m.group(2), int(m.group(3)), m.group(4)
        self.base = f"{self.scheme}://{self.host}:{self.port}"

    def stop(self):
        self.proc.send_signal(signal.SIGINT)
        rest = self.proc.communicate(timeout=30)[0]
        self.log.write(rest)
        self.log.close()
        self.lines += rest.splitlines(keepends=True)
        return self.proc.returncode

    def summary(self):
        for line in self.lines:
            m = re.search(r"refused: (\d+) without token, (\d+) wrong token, (\d+) foreign origin, (\d+) watch token pulling", line)
            if m:
                return tuple(int(x) for x in m.groups())
        return None


def http(url, cookie=None, context=None):
    """(status, headers, body) of a GET."""
    req = urllib.request.Request(url)
    if cookie:
        req.add_header("Cookie", cookie)
    try:
        with urllib.request.urlopen(req, timeout=10, context=context) as r:
            return r.status, r.headers, r.read().decode(errors="replace")
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read().decode(errors="replace")


def ws_status(url, **kw):
    """('open', hello, socket) or (HTTP status of the refused upgrade, None, None)."""
    try:
        s = websocket.create_connection(url, timeout=10, **kw)
    except websocket.WebSocketBadStatusException as e:
        return e.status_code, None, None
    hello = json.loads(s.recv())
    return "open", hello, s


def plain_tests(exe, out):
    d = os.path.join(out, "tokens")
    os.makedirs(d, exist_ok=True)
    pull, watch = "pull-" + "a1" * 12, "watch-" + "b2" * 12
    for name, t in (("pull", pull), ("watch", watch)):
        with open(os.path.join(d, name), "w") as f:
            f.write(t + "\n")
    v = ViewerProc(exe, ["--viewer-token-file", os.path.join(d, "pull"), "--viewer-watch-token-file", os.path.join(d, "watch")],
                   os.path.join(out, "viewer_access_plain.log"))
    try:
        check(v.token == pull, f"the printed URL carries the file's token ({v.url})")
        base, cookie_name = v.base, f"haptree_viewer_{v.port}"
        # HTTP: 3 requests without a token, 2 with a wrong one
        for path in ("/", "/scene.pdb", "/viewer.js"):
            st, _, body = http(base + path)
            check(st == 403, f"GET {path} without token: {st}")
        check("token" in http(base + "/")[2], "the refusal says a token is needed")
        st, _, _ = http(base + "/?token=" + "x" * 48)
        check(st == 403, f"GET / with a wrong token: {st}")
        st, _, _ = http(base + "/scene.pdb", cookie=f"{cookie_name}={'y' * 48}")
        check(st == 403, f"GET /scene.pdb with a wrong cookie: {st}")
        st, hdr, body = http(base + "/?token=" + pull)
        check(st == 200 and "vendor/ngl.js" in body, f"GET / with the token: {st}")
        sc = hdr.get("Set-Cookie", "")
        check(sc.startswith(f"{cookie_name}={pull};") and "HttpOnly" in sc and "SameSite=Strict" in sc,
              f"the page sets its cookie ({sc})")
        st, _, body = http(base + "/scene.pdb", cookie=f"other=1; {cookie_name}={pull}")
        check(st == 200 and body.count("HETATM") == 6, f"GET /scene.pdb with the cookie: {st}")
        st, _, _ = http(base + "/nothing?token=" + pull)
        check(st == 404, f"GET /nothing with the token: {st}")
        st, _, _ = http(base + "/?token=" + watch)
        check(st == 200, f"GET / with the watch token: {st}")

        # WebSocket: 1 without token, 1 wrong token, 2 foreign origins
        ws = f"ws://{v.host}:{v.port}/ws"
        st, _, _ = ws_status(ws)
        check(st == 403, f"WebSocket without token: {st}")
        st, _, _ = ws_status(ws + "?token=" + "z" * 48)
        check(st == 403, f"WebSocket with a wrong token: {st}")
        for origin in ("http://evil.example", f"http://{v.host}:{v.port + 1}"):
            st, _, _ = ws_status(ws + "?token=" + pull, origin=origin)
            check(st == 403, f"WebSocket with the token from Origin {origin}: {st}")
        st, hello, s_pull = ws_status(ws + "?token=" + pull, origin=f"http://{v.host}:{v.port}")
        check(st == "open" and hello["role"] == "pull" and hello["user"] == 0,
              f"WebSocket with the pull token from the page's origin: {st} {hello and (hello['role'], hello['user'])}")
        st, hello, s_cookie = ws_status(ws, cookie=f"{cookie_name}={pull}")
        check(st == "open" and hello["role"] == "pull", f"WebSocket with the cookie only: {st}")
        st, hello, s_watch = ws_status(ws + "?token=" + watch)
        check(st == "open" and hello["role"] == "watch" and hello["user"] == -1,
              f"WebSocket with the watch token: {st} {hello and (hello['role'], hello['user'])}")
        frame = None
        t_end = time.time() + 10
        while time.time() < t_end and frame is None:
            op, data = s_watch.recv_data()
            if op == websocket.ABNF.OPCODE_BINARY or (op == websocket.ABNF.OPCODE_TEXT and b'"frame"' in data):
                frame = data
        check(frame is not None, "the watcher receives frames")
        for _ in range(3):   # three presses: three refusals, one log line
            s_watch.send(json.dumps({"t": "down", "i": 2, "p": [0, 0, 0]}))
        time.sleep(0.5)
        for s in (s_pull, s_cookie, s_watch):
            s.close()
    finally:
        rc = v.stop()
    check(rc == 0, f"viewer exit status {rc}")
    counts = v.summary()
    # no token: 4 HTTP + 1 WebSocket; wrong: 1 query + 1 cookie + 1 WebSocket; origin: 2; watch pull: 3
    check(counts == (5, 3, 2, 3), f"refusals counted (no token, wrong, origin, watch pull) = {counts}, expected (5, 3, 2, 3)")
    logged = [l for l in v.lines if "viewer: refused" in l]
    check(len(logged) == 4, f"each reason logged once for this client: {len(logged)} lines")


def refused_at_start(exe, out):
    tmp = os.path.join(out, "short_token")
    with open(tmp, "w") as f:
        f.write("short\n")
    for args, what, needle in ((["--viewer-no-token", "--viewer-bind", "0.0.0.0"], "--viewer-no-token off the loopback", "needs a token"),
                               (["--viewer-token-file", tmp], "a token file with a 5-character token", "16 to 256")):
        p = subprocess.run([exe, "--lcm-url", "memq://", "--scene", "chain", "--n", "3", "--viewer-port", "0", *args],
                           capture_output=True, text=True, timeout=30)
        text = p.stdout + p.stderr
        check(p.returncode == 1 and needle in text, f"{what} refused at start (exit {p.returncode}: {text.strip()[-120:]!r})")


def tls_tests(exe, out):
    d = os.path.join(out, "tls")
    os.makedirs(d, exist_ok=True)
    cert, key = os.path.join(d, "cert.pem"), os.path.join(d, "key.pem")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                    "-keyout", key, "-out", cert, "-days", "1", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True)
    v = ViewerProc(exe, ["--viewer-tls-cert", cert, "--viewer-tls-key", key], os.path.join(out, "viewer_access_tls.log"))
    browser = None
    try:
        check(v.scheme == "https" and len(v.token) == 48, f"TLS viewer prints an https URL with a random token ({v.url})")

        def s_client(path):
            req = f"GET {path} HTTP/1.1\r\nHost: {v.host}:{v.port}\r\nConnection: close\r\n\r\n"
            p = subprocess.run(["openssl", "s_client", "-connect", f"{v.host}:{v.port}", "-CAfile", cert,
                                "-verify_return_error", "-ign_eof"], input=req, capture_output=True, text=True, timeout=30)
            return p.returncode, p.stdout + p.stderr

        rc, text = s_client("/?token=" + v.token)
        proto = re.search(r"Protocol\s*:\s*(\S+)", text)
        check(rc == 0 and "Verify return code: 0 (ok)" in text and "HTTP/1.1 200" in text,
              f"openssl s_client: handshake {proto.group(1) if proto else '?'}, certificate verified, 200 with the token")
        rc, text = s_client("/")
        check("HTTP/1.1 403" in text, "openssl s_client: 403 without the token")
        ctx = ssl.create_default_context(cafile=cert)
        st, _, body = http(v.base + "/?token=" + v.token, context=ctx)
        check(st == 200 and "vendor/ngl.js" in body, f"https GET with the token (Python ssl, verified): {st}")
        st, hello, s = ws_status(f"wss://{v.host}:{v.port}/ws?token={v.token}", sslopt={"ca_certs": cert},
                                 origin=f"https://{v.host}:{v.port}")
        check(st == "open" and hello["role"] == "pull", f"wss:// with the token: {st}")
        if s:
            s.close()

        browser = cdp.Browser(extra_flags=["--ignore-certificate-errors"])
        page = browser.new_page(v.base + "/")
        time.sleep(2)
        text = page.eval("document.body ? document.body.innerText : ''") or ""
        check("needs its token" in text, f"Chromium without the token sees the refusal ({text.strip()[:60]!r})")
        browser.close_page(page)
        page = browser.new_page(v.base + "/?token=" + v.token)

        def wait(what, fn, timeout=60):
            t_end = time.time() + timeout
            while time.time() < t_end:
                if fn():
                    return True
                time.sleep(0.25)
            check(False, f"timed out waiting for {what}")
            return False

        ds = lambda k: page.eval(f"(document.body && document.body.dataset.{k}) || ''")  # noqa: E731
        if wait("the https page to load", lambda: ds("ready") == "1" and int(ds("frames") or 0) > 0):
            check(True, f"Chromium over https + wss: page ready, {ds('frames')} frames, user {ds('user')}")
        check(page.eval("location.search") == "", "the token is taken off the address bar")
        page.eval("window.beforeReload = 1")
        page.call("Page.reload")
        if wait("the reloaded page", lambda: page.eval("window.beforeReload === undefined") and ds("ready") == "1"
                and int(ds("frames") or 0) > 0):
            check(True, f"reload without the token in the URL (the cookie): ready, {ds('frames')} frames")
    finally:
        if browser:
            browser.quit()
        rc = v.stop()
    check(rc == 0, f"TLS viewer exit status {rc}")
    counts = v.summary()
    # without token: s_client's GET /, Chromium's GET / and, where it asks for one before the cookie, its
    # /favicon.ico
    check(counts is not None and counts[0] in (2, 3) and counts[1:] == (0, 0, 0),
          f"TLS viewer refusals: 2-3 without token (s_client, Chromium), nothing else: {counts}")


def main():
    exe, out = sys.argv[1], sys.argv[2]
    os.makedirs(out, exist_ok=True)
    for part in (plain_tests, refused_at_start, tls_tests):
        try:
            part(exe, out)
        except Exception as e:  # a failed wait, a crash: reported with what ran before
            failures.append(f"{part.__name__}: {e!r}")
            print("FAIL", part.__name__, repr(e), flush=True)
    if failures:
        print(f"{len(failures)} failure(s)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

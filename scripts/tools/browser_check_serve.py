"""Drive ``nvp serve``'s page in a real browser: headless Chromium (Debian packages ``chromium`` and
``chromium-driver``, Python ``selenium``) uploads a video, watches the fit, dubs the person with audio and
with text, and plays the result; a screenshot of every step goes to ``--out``. Along the way it checks the
server's local-app security from the browser's side: the page works with its token, an API call without
the token is refused, a DNS-rebound host name gets no page (and so no token), a page on another site
cannot make the server do anything, and the page's Content-Security-Policy blocks nothing of its own.

    python -m scripts.tools.browser_check_serve --video ../shared/data/video/X.mp4 --audio speech.wav \
        [--minutes 1] [--out out/browser]

Starts its own server on a free port with a fresh data folder under ``--out`` (the attacker's page on a
second port; Chromium maps the names ``rebind.test`` and ``evil.test`` to 127.0.0.1). Exit code 0 when
every step worked; each step prints what the page showed.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

EVIL_PAGE = """<!doctype html><title>cat pictures</title><body>
<form id="f" method="POST" enctype="text/plain" action="http://127.0.0.1:{port}/api/people?name=evil">
<input name="x" value="y"></form>
<script>
const api = "http://127.0.0.1:{port}/api";
Promise.allSettled([
  fetch(api + "/people?name=evil",
        {{method: "POST", mode: "no-cors", body: "x", headers: {{"Content-Type": "text/plain"}}}}),
  fetch(api + "/people/p-000000000000", {{method: "DELETE", mode: "no-cors"}}),
  fetch(api + "/people", {{mode: "cors"}}).then((r) => r.text()).then((t) => {{ window.leak = t; }}),
]).then(() => {{ document.title = "sent"; document.getElementById("f").submit(); }});
</script></body>"""


def _evil_server(port: int) -> ThreadingHTTPServer:
    """A page on another site (another origin) that tries to use the app's API."""
    page = EVIL_PAGE.format(port=port).encode()

    class Evil(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args) -> None:
            return None

    server = ThreadingHTTPServer(("127.0.0.1", 0), Evil)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--video", type=Path, required=True)
    ap.add_argument("--audio", type=Path, required=True)
    ap.add_argument("--text", default="Peter Piper picked a peck of pickled peppers.")
    ap.add_argument("--minutes", type=float, default=1.0, help="renderer training minutes of the fit")
    ap.add_argument("--out", type=Path, default=Path("out/browser"))
    ap.add_argument("--timeout", type=float, default=1800, help="seconds to wait for a job")
    args = ap.parse_args(argv)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    from nvp.app.serve import App, make_server

    args.out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(args.out / "data", ignore_errors=True)  # this script's own folder: a fresh start
    for old in args.out.glob("[0-9][0-9]_*.png"):
        old.unlink()
    app = App(args.out / "data")
    server = make_server(app, "127.0.0.1", 0)
    answered: list[tuple[str, str, str, int]] = []  # (method, path, Origin, status) of every request

    def record(handler, code="-", size="-") -> None:
        origin = handler.headers.get("Origin", "") if getattr(handler, "headers", None) else ""
        answered.append((handler.command or "", (handler.path or "").split("?")[0], origin, int(code)))

    server.RequestHandlerClass.log_request = record
    port = server.server_address[1]
    threading.Thread(target=server.serve_forever, daemon=True).start()
    app.worker.start()
    evil = _evil_server(port)
    url = f"http://127.0.0.1:{port}/"
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--window-size=1280,1000",
        "--autoplay-policy=no-user-gesture-required",
        "--host-resolver-rules=MAP rebind.test 127.0.0.1, MAP evil.test 127.0.0.1",
    ):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    n = 0
    failures: list[str] = []
    console: list[str] = []

    def shot(name: str) -> None:
        nonlocal n
        n += 1
        path = args.out / f"{n:02d}_{name}.png"
        driver.save_screenshot(str(path))
        print(f"screenshot {path}")

    def check(ok: bool, what: str) -> None:
        print(("ok:   " if ok else "FAIL: ") + what)
        if not ok:
            failures.append(what)

    def wait_for(text_of, predicate, what: str, timeout: float) -> str:
        end = time.time() + timeout
        last = ""
        while time.time() < end:
            last = text_of()
            if predicate(last):
                return last
            time.sleep(1.0)
        raise SystemExit(f"timed out waiting for {what}; the page shows: {last[:300]}")

    def logs() -> None:
        console.extend(f"{e['level']} {e['message']}" for e in driver.get_log("browser"))

    ok = False
    try:
        driver.get(url)
        shot("empty")
        token = driver.execute_script("return document.querySelector('meta[name=\"nvp-token\"]').content")
        check(token == app.token, "the page carries this launch's token")
        status = driver.execute_async_script(
            "const done = arguments[0];"
            "fetch('/api/people').then((r) => done(r.status), (e) => done(String(e)));"
        )
        check(status == 401, f"an API call from the page without the token is refused ({status})")
        status = driver.execute_async_script(
            "const done = arguments[0]; fetch('/api/people', {headers: {'X-NVP-Token': token}})"
            ".then((r) => done(r.status), (e) => done(String(e)));"
        )
        check(status == 200, f"the same call with the token is answered ({status})")
        # DNS rebinding: another host name that resolves to 127.0.0.1 gets no page, so no token
        driver.get(f"http://rebind.test:{port}/")
        body = driver.find_element(By.TAG_NAME, "body").text
        shot("rebound_name_refused")
        check(
            "nvp-token" not in driver.page_source and "answers requests for" in body,
            f"rebound name: {body[:90]}",
        )
        # a page on another site tries a text/plain upload, a DELETE, a read and a form post
        before = len(answered)
        driver.get(f"http://evil.test:{evil.server_address[1]}/")
        wait_for(lambda: driver.title, lambda t: t != "cat pictures", "the other site's page to send", 30)
        time.sleep(2)  # the form's navigation
        shot("other_site_refused")
        tried = [a for a in answered[before:] if a[1].startswith("/api/")]
        print("other site's requests:", tried)
        check(
            bool(tried) and all(a[3] == 403 and "evil.test" in a[2] for a in tried),
            f"every request from the other site that arrived was refused 403 ({len(tried)} arrived)",
        )
        check(app.store.all() == [] and app.names() == {}, "the other site's page made no person and no job")
        driver.get(url)
        driver.find_element(By.ID, "video").send_keys(str(args.video.resolve()))
        driver.find_element(By.ID, "name").send_keys(args.video.stem)
        driver.find_element(By.ID, "minutes").send_keys(str(args.minutes))
        driver.find_element(By.ID, "fit").click()
        jobs = lambda: driver.find_element(By.ID, "jobs").text  # noqa: E731
        seen = wait_for(jobs, lambda t: "running" in t or "failed" in t, "the fit to start", 120)
        print("fit started:", " ".join(seen.split()))
        wait_for(jobs, lambda t: "train renderer" in t or "failed" in t, "renderer training", args.timeout)
        preview = "const p = document.querySelector('.preview'); return p && p.complete && p.naturalWidth > 0"
        wait_for(lambda: driver.execute_script(preview), bool, "a renderer preview", 60 * args.minutes + 120)
        shot("fit_running")
        print("fit running:", " ".join(jobs().split()))
        wait_for(
            jobs, lambda t: "done" in t or "failed" in t, "the fit to end", args.timeout + 60 * args.minutes
        )
        time.sleep(2)
        shot("person_ready")
        people = driver.find_element(By.ID, "people").text
        print("people:", " ".join(people.split()))
        if "ready" not in people:
            raise SystemExit("the fit did not make a ready person")
        thumb = driver.execute_script(
            "const i = document.querySelector('.person img'); return i.naturalWidth"
        )
        check(thumb > 0, "the person's thumbnail loads (its URL carries the token)")
        check(not any((app.data / "uploads").iterdir()), "the fit's upload is gone once the fit is done")
        driver.find_element(By.CSS_SELECTOR, "[data-pick]").click()
        driver.find_element(By.ID, "audio").send_keys(str(args.audio.resolve()))
        driver.find_element(By.ID, "dub").click()
        wait_for(jobs, lambda t: t.count("done") >= 2 or "failed" in t, "the dub", args.timeout)
        driver.find_element(By.CSS_SELECTOR, "[data-play]").click()
        wait_for(
            lambda: driver.execute_script(
                "const v = document.getElementById('player'); return v && v.readyState"
            ),
            lambda s: s and s >= 2,
            "the player to load",
            60,
        )
        time.sleep(2)
        shot("dub_playing")
        result = driver.find_element(By.ID, "result").text
        playing = driver.execute_script(
            "const v = document.getElementById('player');"
            "return v ? [v.readyState, v.duration, v.currentTime] : null"
        )
        print("result:", " ".join(result.split()), "| video readyState, duration, time:", playing)
        check(
            "SYNTHETIC" in result and bool(playing) and playing[1] > 0, "the dub plays, marked as synthetic"
        )
        driver.find_element(By.ID, "text").send_keys(args.text)
        driver.find_element(By.ID, "say").click()
        wait_for(jobs, lambda t: t.count("done") >= 3 or "failed" in t, "the text dub", args.timeout)
        time.sleep(2)
        shot("say_done")
        print("jobs:", " ".join(jobs().split()))
        check("failed" not in jobs(), "no job failed")
        logs()
        csp = [m for m in console if "Content Security Policy" in m]
        check(not csp, f"the page's policy blocked nothing of its own ({csp[:2]})")
        refused = [m for m in console if " 401 " in m or " 403 " in m]
        print(f"console: {len(console)} entries; refused loads: {refused[:3]}")
        ok = not failures
    finally:
        driver.quit()
        evil.shutdown()
        server.shutdown()
        app.close()
    print("browser check:", "passed" if ok else f"FAILED ({'; '.join(failures)})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

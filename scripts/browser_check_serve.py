"""Drive ``nvp serve``'s page in a real browser: headless Chromium (Debian packages ``chromium`` and
``chromium-driver``, Python ``selenium``) uploads a video, watches the fit, dubs the person with audio and
with text, and plays the result; a screenshot of every step goes to ``--out``.

    python scripts/browser_check_serve.py --video ../shared/data/video/X.mp4 --audio speech.wav \
        [--minutes 1] [--out out/browser]

Starts its own server on a free port with a fresh data folder under ``--out``. Exit code 0 when every step
worked; each step prints what the page showed.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path


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
    app = App(args.out / "data")
    server = make_server(app, "127.0.0.1", 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    app.worker.start()
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--window-size=1280,1000",
        "--autoplay-policy=no-user-gesture-required",
    ):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    n = 0

    def shot(name: str) -> None:
        nonlocal n
        n += 1
        path = args.out / f"{n:02d}_{name}.png"
        driver.save_screenshot(str(path))
        print(f"screenshot {path}")

    def wait_for(text_of, predicate, what: str, timeout: float) -> str:
        end = time.time() + timeout
        last = ""
        while time.time() < end:
            last = text_of()
            if predicate(last):
                return last
            time.sleep(1.0)
        raise SystemExit(f"timed out waiting for {what}; the page shows: {last[:300]}")

    try:
        driver.get(url)
        shot("empty")
        driver.find_element(By.ID, "video").send_keys(str(args.video.resolve()))
        driver.find_element(By.ID, "name").send_keys(args.video.stem)
        driver.find_element(By.ID, "minutes").send_keys(str(args.minutes))
        driver.find_element(By.ID, "fit").click()
        jobs = lambda: driver.find_element(By.ID, "jobs").text  # noqa: E731
        seen = wait_for(jobs, lambda t: "running" in t, "the fit to start", 60)
        print("fit started:", " ".join(seen.split()))
        wait_for(jobs, lambda t: "train renderer" in t, "renderer training", args.timeout)
        time.sleep(35)  # a preview image is written every 500 steps
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
        driver.find_element(By.CSS_SELECTOR, "[data-pick]").click()
        driver.find_element(By.ID, "audio").send_keys(str(args.audio.resolve()))
        driver.find_element(By.ID, "dub").click()
        wait_for(jobs, lambda t: t.count("done") >= 2 or "failed" in t, "the dub", args.timeout)
        driver.find_element(By.CSS_SELECTOR, "[data-play]").click()
        time.sleep(3)
        shot("dub_playing")
        result = driver.find_element(By.ID, "result").text
        playing = driver.execute_script(
            "const v = document.getElementById('player');"
            "return v ? [v.readyState, v.duration, v.currentTime] : null"
        )
        print("result:", " ".join(result.split()), "| video readyState, duration, time:", playing)
        driver.find_element(By.ID, "text").send_keys(args.text)
        driver.find_element(By.ID, "say").click()
        wait_for(jobs, lambda t: t.count("done") >= 3 or "failed" in t, "the text dub", args.timeout)
        time.sleep(2)
        shot("say_done")
        print("jobs:", " ".join(jobs().split()))
        ok = "failed" not in jobs() and "SYNTHETIC" in result and playing and playing[1] > 0
    finally:
        driver.quit()
        server.shutdown()
        app.worker.stop()
    print("browser check:", "passed" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

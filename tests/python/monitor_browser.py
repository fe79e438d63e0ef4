"""Drives the coordinator's web monitor in a headless browser, for
tests/monitor.rs: Chromium (Selenium with Debian's chromium and
chromium-driver) or Firefox (Debian's firefox-esr and geckodriver, which
`scripts/test` builds from crates.io).

The Rust test starts the coordinator and the workers; this script submits
jobs with the `tessera` binary and checks everything else through the page
a person would use: sign-in, a failed job's workers' messages, the jobs
list, a job's settings, progress and live preview, full size and download,
the workers page, cancel, an animation's frame thumbnails. It prints one line per step and exits
non-zero (with the reason) on the first failure.

Written for the test (argument names are the Rust side's), but it can be run
by hand against any coordinator started with --http.
"""

import argparse
import base64
import hashlib
import json
import os
import signal
import subprocess
import sys
import time

from selenium import webdriver
from selenium.webdriver.chrome.options import Options as ChromeOptions
from selenium.webdriver.chrome.service import Service as ChromeService
from selenium.webdriver.common.by import By
from selenium.webdriver.firefox.options import Options as FirefoxOptions
from selenium.webdriver.firefox.service import Service as FirefoxService


def step(msg):
    print(f"[monitor] {msg}", flush=True)


def fail(msg):
    print(f"[monitor] FAILED: {msg}", flush=True)
    sys.exit(1)


def wait(what, timeout, f, poll=0.1):
    end = time.time() + timeout
    while True:
        v = f()
        if v:
            return v
        if time.time() > end:
            fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(poll)


class Page:
    def __init__(self, browser, binary, driver, width, height, dark=False, downloads=None):
        """`dark`: the system theme the page sees (Firefox takes it at start);
        `downloads`: the folder the browser saves downloads to, unasked."""
        self.browser = browser
        if browser == "chromium":
            o = ChromeOptions()
            o.binary_location = binary
            for a in (
                "--headless=new",
                "--no-sandbox",
                "--disable-dev-shm-usage",
                "--disable-gpu",
                # Pixels read back from a canvas are the image's, unconverted.
                "--force-color-profile=srgb",
                "--hide-scrollbars",
                f"--window-size={width},{height}",
            ):
                o.add_argument(a)
            if downloads:
                o.add_experimental_option("prefs", {
                    "download.default_directory": downloads,
                    "download.prompt_for_download": False,
                })
            self.d = webdriver.Chrome(service=ChromeService(executable_path=driver), options=o)
            if downloads:
                self.d.execute_cdp_cmd("Page.setDownloadBehavior",
                                       {"behavior": "allow", "downloadPath": downloads})
            if dark:
                self.d.execute_cdp_cmd("Emulation.setEmulatedMedia", {
                    "features": [{"name": "prefers-color-scheme", "value": "dark"}]})
        else:
            o = FirefoxOptions()
            o.binary_location = binary
            o.add_argument("-headless")
            # 0: dark, 1: light, whatever the (headless) system says.
            o.set_preference("layout.css.prefers-color-scheme.content-override", 0 if dark else 1)
            # Pixels read back from a canvas are the image's, unconverted.
            o.set_preference("gfx.color_management.mode", 0)
            if downloads:
                o.set_preference("browser.download.folderList", 2)
                o.set_preference("browser.download.dir", downloads)
                o.set_preference("browser.download.useDownloadDir", True)
                o.set_preference("browser.download.always_ask_before_handling_new_types", False)
                o.set_preference("browser.helperApps.neverAsk.saveToDisk", "image/png")
                o.set_preference("browser.download.manager.showWhenStarting", False)
            self.d = webdriver.Firefox(service=FirefoxService(executable_path=driver), options=o)
            self.d.set_window_size(width, height)
        self.d.set_script_timeout(30)

    def go(self, url):
        self.d.get(url)

    def js(self, script, *args):
        return self.d.execute_script(script, *args)

    def ajs(self, script, *args):
        return self.d.execute_async_script(script, *args)

    def css(self, sel):
        return self.d.find_elements(By.CSS_SELECTOR, sel)

    def attr(self, sel, name):
        return self.js(
            "const e = document.querySelector(arguments[0]); return e ? e.getAttribute(arguments[1]) : null;",
            sel,
            name,
        )

    def text(self, sel):
        return self.js(
            "const e = document.querySelector(arguments[0]); return e ? e.textContent : null;", sel
        )

    def click(self, sel):
        wait(f"{sel} to be clickable", 10, lambda: self.js(
            "const e = document.querySelector(arguments[0]); return !!e && !e.disabled;", sel))
        self.css(sel)[0].click()

    def image_dataset_pixels(self, sel):
        """An image as the page shows it and what its dataset says, read in
        one go (the page may swap the image between two reads):
        (width, height, RGBA bytes, dataset dict), or None while not loaded."""
        r = self.js(
            """
            const img = document.querySelector(arguments[0]);
            if (!img || !img.complete || !img.naturalWidth) return null;
            const c = document.createElement('canvas');
            c.width = img.naturalWidth; c.height = img.naturalHeight;
            const g = c.getContext('2d');
            g.drawImage(img, 0, 0);
            const d = g.getImageData(0, 0, c.width, c.height).data;
            let s = '';
            for (let i = 0; i < d.length; i += 8192) s += String.fromCharCode.apply(null, d.subarray(i, i + 8192));
            return [c.width, c.height, btoa(s), Object.assign({}, img.dataset)];
            """, sel)
        return (r[0], r[1], base64.b64decode(r[2]), r[3]) if r else None

    def image_pixels(self, sel):
        """An image as the page shows it: (width, height, RGBA bytes), or None
        while it is not loaded."""
        r = self.image_dataset_pixels(sel)
        return r[:3] if r else None

    def settings(self):
        """The job page's settings list, label -> value."""
        return self.js(
            "const o = {}; document.querySelectorAll('#settings dt').forEach("
            "dt => { o[dt.textContent] = dt.nextElementSibling.textContent; }); return o;")

    def preview_pixels(self):
        """The preview as the page shows it: (width, height, RGBA bytes,
        version, units done, written)."""
        r = self.image_dataset_pixels("#preview")
        if not r:
            return None
        w, h, data, ds = r
        return w, h, data, int(ds.get("version") or 0), ds.get("unitsDone"), ds.get("written") == "1"

    def shot(self, path):
        if path:
            self.d.save_screenshot(path)
            step(f"screenshot {path}")

    def quit(self):
        self.d.quit()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--http", required=True, help="the monitor's URL")
    ap.add_argument("--grpc", required=True, help="the coordinator's gRPC URL (for tessera submit)")
    ap.add_argument("--token", required=True)
    ap.add_argument("--tessera", required=True, help="the tessera binary")
    ap.add_argument("--scene", required=True)
    ap.add_argument("--settings", required=True, help="JSON list of submit arguments for the first job")
    ap.add_argument("--second-settings", required=True, help="JSON list for the job cancelled from the page")
    ap.add_argument("--failed-job", required=True, help="a job failed by a worker's message, before the page opens")
    ap.add_argument("--failed-message", required=True, help="the worker's message that failed it")
    ap.add_argument("--anim-scene", required=True, help="an animated scene, for the frame thumbnails")
    ap.add_argument("--anim-settings", required=True, help="JSON list of submit arguments for it (--frames A..B)")
    ap.add_argument("--model-scene", help="a textured model file (glTF) submitted directly, shown whole in the preview")
    ap.add_argument("--model-settings", default="[]", help="JSON list of submit arguments for it")
    ap.add_argument("--victim-pid", type=int, required=True, help="a worker to SIGKILL mid-job")
    ap.add_argument("--victim-name", required=True)
    ap.add_argument("--out", required=True, help="folder for results and screenshots")
    ap.add_argument("--browser", choices=["chromium", "firefox"], default="chromium")
    ap.add_argument("--binary", help="the browser [default: /usr/bin/chromium or /usr/bin/firefox-esr]")
    ap.add_argument("--driver", help="chromedriver or geckodriver [default: /usr/bin/chromedriver or geckodriver on PATH]")
    a = ap.parse_args()
    if a.browser == "chromium":
        a.binary = a.binary or os.environ.get("CHROMIUM", "/usr/bin/chromium")
        a.driver = a.driver or os.environ.get("CHROMEDRIVER", "/usr/bin/chromedriver")
    else:
        a.binary = a.binary or os.environ.get("FIREFOX", "/usr/bin/firefox-esr")
        a.driver = a.driver or os.environ.get("GECKODRIVER", "geckodriver")

    env = dict(os.environ, TESSERA_COORDINATOR=a.grpc, TESSERA_TOKEN=a.token)

    def submit(args, name, scene=None):
        r = subprocess.run(
            [a.tessera, "submit", scene or a.scene, "--name", name] + args,
            env=env, capture_output=True, text=True, timeout=120,
        )
        if r.returncode != 0:
            fail(f"tessera submit: {r.stderr}")
        return r.stdout.strip()

    def shot(page, name):
        page.shot(os.path.join(a.out, name))

    downloads = os.path.join(a.out, "downloads")
    os.makedirs(downloads, exist_ok=True)
    p = Page(a.browser, a.binary, a.driver, 1280, 1000, downloads=downloads)
    step(f"browser: {a.browser} {p.d.capabilities.get('browserVersion', '?')}")
    try:
        # -- sign-in: nothing of the farm before the token ------------------
        p.go(a.http + "/")
        wait("the sign-in form", 15, lambda: p.css("#token"))
        if p.css("#jobs") or p.js("return !document.querySelector('#nav').hidden"):
            fail("jobs or navigation visible before the token was given")
        r = p.ajs(
            "const done = arguments[arguments.length - 1];"
            "fetch('/api/jobs').then(r => done(r.status));"
        )
        if r != 401:
            fail(f"/api/jobs without the token answered {r}, not 401")
        p.css("#token")[0].send_keys("not-the-token")
        p.click("#login-form button")
        wait("the wrong token refused", 10, lambda: "not this coordinator" in (p.text("#login-error") or ""))
        p.css("#token")[0].clear()
        p.css("#token")[0].send_keys(a.token)
        p.click("#login-form button")
        wait("the jobs page", 15, lambda: p.css("#no-jobs") or p.css("#jobs"))
        wait("live updates", 10, lambda: "on" in (p.attr("#live", "class") or ""))
        step("signed in; jobs page live")

        # -- a job a worker failed: its error and the worker's message -------
        p.go(f"{a.http}/#/jobs/{a.failed_job}")
        wait("the failed job's page", 10, lambda: p.attr("#job-state", "data-state") == "failed")
        wait("the job's error", 10, lambda: a.failed_message in (p.text("#job-error") or ""))
        wait("the failures list", 10, lambda: p.css("#failures ul.failures code"))
        failures = p.js("return [...document.querySelectorAll('#failures ul.failures > li')]"
                        ".map(li => [li.firstChild.textContent.trim(), [...li.querySelectorAll('code')].map(c => c.textContent)])")
        if len(failures) != 1 or not failures[0][0].startswith("Unit 0: frame 0") \
                or failures[0][1] != [f"worker flaky: {a.failed_message}",
                                      f"worker flaky-too: {a.failed_message}"]:
            fail(f"the failures list shows {failures}, not unit 0 with workers flaky's and flaky-too's messages")
        if not p.js("return document.querySelector('#cancel').disabled"):
            fail("the cancel button is enabled on a failed job")
        step(f"the failed job shows the worker's message: {failures[0][1][0]!r}")
        p.go(f"{a.http}/#/jobs")
        wait("the jobs list", 10, lambda: p.css(f'tr[data-job="{a.failed_job}"]'))

        # -- a job appears, progresses, and its preview fills in ------------
        job = submit(json.loads(a.settings), "monitor-first")
        step(f"submitted {job}")
        wait("the job in the list", 15, lambda: p.css(f'tr[data-job="{job}"]'))
        step("the job is listed")
        p.go(f"{a.http}/#/jobs/{job}")
        wait("the job page", 10, lambda: p.css("#job-state"))
        # The settings list says what was submitted.
        given = dict(zip(json.loads(a.settings)[::2], json.loads(a.settings)[1::2]))
        want = {
            "Scene": a.scene,  # as submitted
            "Size": f"{given['--width']} × {given['--height']}",
            "Samples": given["--samples"],
            "Tile size": given["--tile-size"],
            "Samples a unit": given["--samples-per-unit"],
            "Frames": "0",
        }
        shown = wait("the settings list", 10, lambda: p.settings())
        wrong = {k: (v, shown.get(k)) for k, v in want.items() if shown.get(k) != v}
        if wrong:
            fail(f"settings shown differ from those submitted (wanted, shown): {wrong}; all shown: {shown}")
        step(f"settings listed: {shown}")
        progress, images = [], {}
        mid_shot = False
        killed = False
        end = time.time() + 240
        while True:
            state = p.attr("#job-state", "data-state")
            v = float(p.attr("#job-progress", "data-value") or 0)
            if not progress or v != progress[-1]:
                progress.append(v)
            px = p.preview_pixels()
            if px and state == "running" and not px[5]:
                images.setdefault(hashlib.sha256(px[2]).hexdigest(), px[3])
            rising = len(progress) >= 3 and progress == sorted(progress)
            # For the docs: a moment with tiles leased and tiles not started
            # (the first sample batch), else any moment mid-job.
            if not mid_shot and px and (
                (v >= 0.05 and p.css("#overlay .tile.pending") and p.css("#overlay .tile.leased"))
                or (0.3 <= v <= 0.7 and p.css("#overlay .tile"))
            ):
                shot(p, "job-preview.png")
                mid_shot = True
            if not killed and len(images) >= 2 and rising and v < 0.9:
                # Mid-job: one worker dies without a word.
                p.go(f"{a.http}/#/workers")
                wait("the workers page", 10, lambda: p.css(f'tr[data-worker-name="{a.victim_name}"]'))
                # Each worker's row: what it is, and what it did (the flaky
                # worker failed the first job's unit and left).
                rows = p.js(
                    "const o = {}; document.querySelectorAll('#workers tbody tr').forEach(tr => {"
                    " const r = {state: tr.dataset.state}; tr.querySelectorAll('td').forEach(td => {"
                    " r[td.dataset.label] = td.firstChild ? td.firstChild.textContent.trim() : ''; });"
                    " o[tr.dataset.workerName] = r; }); return o;")
                for name in ("steady", a.victim_name):
                    r = rows.get(name, {})
                    if (r.get("Backend"), r.get("Threads"), r.get("Units failed")) != ("cpu", "1", "0") \
                            or int(r.get("Units done") or 0) < 1 or "samples/s" not in r.get("Speed", "") \
                            or r.get("Speed", "").startswith("0 ") or r.get("state") == "gone":
                        fail(f"worker {name}'s row: {r}")
                flaky = rows.get("flaky", {})
                if (flaky.get("Units done"), flaky.get("Units failed"), flaky.get("state")) != ("0", "1", "gone"):
                    fail(f"the flaky worker's row: {flaky}")
                step(f"workers listed: {rows}")
                shot(p, "workers.png")
                os.kill(a.victim_pid, signal.SIGKILL)
                step(f"killed worker {a.victim_name} (pid {a.victim_pid}) at {v:.0%}")
                killed = True
                wait(f"{a.victim_name} shown gone", 30, lambda: p.attr(
                    f'tr[data-worker-name="{a.victim_name}"]', "data-state") == "gone")
                step(f"the workers page shows {a.victim_name} gone")
                shot(p, "workers-gone.png")
                p.go(f"{a.http}/#/jobs/{job}")
                wait("the job page", 10, lambda: p.css("#job-state"))
            if state in ("failed", "cancelled"):
                fail(f"the job ended {state}: {p.text('#job-error')}")
            if state == "done":
                break
            if time.time() > end:
                fail(f"the job did not finish: progress {progress}")
            time.sleep(0.15)
        step(f"progress seen: {['%.3f' % x for x in progress]}")
        if not killed:
            fail(f"the job ended before the checks could run mid-job (progress {progress}, {len(images)} preview images); make it longer")
        if len(progress) < 3 or progress != sorted(progress) or progress[-1] != 1.0:
            fail(f"progress did not rise to 1: {progress}")
        if len(images) < 2:
            fail(f"the preview did not change while the job ran ({len(images)} distinct images)")
        step(f"{len(images)} distinct preview images while the job ran")
        if not mid_shot:
            fail("no mid-render moment for the preview screenshot")

        # The finished frame, as the page shows it.
        px = wait("the preview of the written frame", 20,
                  lambda: (lambda x: x if x and x[5] else None)(p.preview_pixels()))
        w, h, rgba = px[0], px[1], px[2]
        with open(os.path.join(a.out, "preview.rgba"), "wb") as f:
            f.write(rgba)
        with open(os.path.join(a.out, "preview.json"), "w") as f:
            json.dump({"job": job, "width": w, "height": h}, f)
        step(f"final preview {w}x{h} saved")
        # Full size and download work (a blob of PNG bytes).
        p.click("#full-size")
        wait("the full-size viewer", 10, lambda: p.js(
            "const v = document.querySelector('#viewer'); const i = document.querySelector('#viewer-img');"
            "return !v.hidden && i.complete && i.naturalWidth > 0;"))
        nat = p.js("const i = document.querySelector('#viewer-img'); return [i.naturalWidth, i.naturalHeight];")
        if nat != [w, h]:
            fail(f"full-size view is {nat}, the preview {w}x{h}")
        p.click("#viewer-close")
        step("full-size view opens")
        # Download PNG saves the written frame under a name that says what it is.
        name = f"{job}_frame_0000.png"
        p.click("#download")
        saved = os.path.join(downloads, name)
        wait(f"{name} downloaded", 20, lambda: os.path.exists(saved)
             and not any(f.endswith((".crdownload", ".part")) for f in os.listdir(downloads))
             and os.path.getsize(saved) > 0)
        with open(os.path.join(a.out, "download.json"), "w") as f:
            json.dump({"job": job, "path": saved}, f)
        disposition = p.ajs(
            "const done = arguments[arguments.length - 1];"
            "fetch(arguments[0], {headers: {Authorization: 'Bearer ' + sessionStorage.getItem('tessera-client-token')}})"
            ".then(r => done(r.headers.get('content-disposition')), () => done(null));",
            f"/api/jobs/{job}/frames/0/image.png?download=1")
        if disposition != f'attachment; filename="{name}"':
            fail(f"?download=1 answers Content-Disposition {disposition!r}")
        step(f"downloaded {name} ({os.path.getsize(saved)} bytes)")

        # -- cancel from the page stops a second job -------------------------
        job2 = submit(json.loads(a.second_settings), "monitor-cancelled")
        step(f"submitted {job2}")
        p.go(f"{a.http}/#/jobs/{job2}")
        wait("the second job running with results", 120, lambda: p.attr("#job-state", "data-state") == "running"
             and float(p.attr("#job-progress", "data-value") or 0) > 0)
        # The jobs page with one job done and one running.
        p.go(f"{a.http}/#/jobs")
        wait("the jobs table", 10, lambda: p.css(f'tr[data-job="{job2}"]'))
        shot(p, "jobs.png")
        p.go(f"{a.http}/#/jobs/{job2}")
        wait("the job page", 10, lambda: p.css("#cancel"))
        # The priority control changes the farm's priority.
        p.css("#priority")[0].clear()
        p.css("#priority")[0].send_keys("7")
        p.click("#set-priority")
        wait("priority 7 in the farm", 10, lambda: p.ajs(
            "const done = arguments[arguments.length - 1];"
            "fetch('/api/jobs/' + arguments[0], {headers: {Authorization: 'Bearer ' + sessionStorage.getItem('tessera-client-token')}})"
            ".then(r => r.json()).then(j => done(j.priority), () => done(null));", job2) == 7)
        step("priority set to 7 from the page")
        p.click("#cancel")
        wait("the cancel button to ask for confirmation", 5, lambda: "armed" in (p.attr("#cancel", "class") or ""))
        p.click("#cancel")
        wait("the job cancelled", 15, lambda: p.attr("#job-state", "data-state") == "cancelled")
        stopped_at = float(p.attr("#job-progress", "data-value") or 0)
        if stopped_at >= 1.0:
            fail("the second job finished before it could be cancelled; make it longer")
        time.sleep(2.0)
        after = float(p.attr("#job-progress", "data-value") or 0)
        if after != stopped_at:
            fail(f"progress moved after the cancel: {stopped_at} -> {after}")
        if not p.js("return document.querySelector('#cancel').disabled"):
            fail("the cancel button is still enabled on a cancelled job")
        with open(os.path.join(a.out, "cancelled.json"), "w") as f:
            json.dump({"job": job2, "progress": stopped_at}, f)
        step(f"cancelled {job2} from the page at {stopped_at:.0%}; it stays there")

        # -- an animation: one thumbnail per frame, a click shows that frame --
        anim_args = json.loads(a.anim_settings)
        first, last = (int(x) for x in anim_args[anim_args.index("--frames") + 1].split(".."))
        frames = list(range(first, last + 1))
        job3 = submit(anim_args, "monitor-animation", a.anim_scene)
        step(f"submitted {job3} (frames {first}..{last})")
        p.go(f"{a.http}/#/jobs/{job3}")
        wait("the animation done", 120, lambda: p.attr("#job-state", "data-state") == "done")
        # An adaptive job's settings: its sample bounds and targets, and
        # how much of it converged.
        given = dict(zip(anim_args[::2], anim_args[1::2]))
        if "--target-error" in given:
            want = {
                "Samples": f"{given['--min-samples']}–{given['--max-samples']} (adaptive)",
                "Target error": given["--target-error"],
                "Relative error": given["--relative-error"],
            }
            shown = wait("the settings list", 10, lambda: p.settings())
            wrong = {k: (v, shown.get(k)) for k, v in want.items() if shown.get(k) != v}
            if wrong:
                fail(f"adaptive settings shown differ (wanted, shown): {wrong}; all shown: {shown}")
            converged = p.text("#job-converged") or ""
            if not converged.endswith("%"):
                fail(f"no converged share for an adaptive job: {converged!r}")
            step(f"adaptive job's settings listed, {converged} of blocks converged")
        thumbs = {}
        for fr in frames:
            sel = f'#frames [data-frame="{fr}"] img[data-written="1"]'
            thumbs[fr] = wait(f"frame {fr}'s thumbnail", 20, lambda: p.image_pixels(sel))
            cap = p.text(f'#frames [data-frame="{fr}"] .cap')
            if cap != f"{fr} · done":
                fail(f"frame {fr}'s caption is {cap!r}")
        if len({hashlib.sha256(t[2]).hexdigest() for t in thumbs.values()}) != len(frames):
            fail("thumbnails of different frames of the animation are the same image")
        meta = {}
        for fr, (w, h, rgba) in thumbs.items():
            with open(os.path.join(a.out, f"thumb_{fr}.rgba"), "wb") as f:
                f.write(rgba)
            meta[fr] = [w, h]
        with open(os.path.join(a.out, "thumbs.json"), "w") as f:
            json.dump({"job": job3, "frames": meta}, f)
        # Clicking a thumbnail shows that frame in the preview.
        pick = frames[0]
        p.css(f'#frames [data-frame="{pick}"]')[0].click()
        wait(f"frame {pick} in the preview", 10, lambda: p.text("#preview-frame") == str(pick)
             and p.attr("#preview", "data-frame") == str(pick) and p.attr("#preview", "data-written") == "1")
        if p.image_pixels("#preview")[2] != thumbs[pick][2]:
            fail(f"the preview of frame {pick} after a click differs from its thumbnail")
        step(f"{len(frames)} thumbnails, one per frame; a click shows frame {pick}")

        # -- a textured model file, submitted as it is: its finished frame --
        if a.model_scene:
            job4 = submit(json.loads(a.model_settings), "monitor-model", a.model_scene)
            step(f"submitted {job4} ({a.model_scene})")
            p.go(f"{a.http}/#/jobs/{job4}")
            wait("the model job done", 120, lambda: p.attr("#job-state", "data-state") == "done")
            shown = wait("the settings list", 10, lambda: p.settings())
            given = dict(zip(json.loads(a.model_settings)[::2], json.loads(a.model_settings)[1::2]))
            want = {"Scene": a.model_scene, "Integrator": given.get("--integrator", "whitted"),
                    "Samples": given.get("--samples")}
            wrong = {k: (v, shown.get(k)) for k, v in want.items() if shown.get(k) != v}
            if wrong:
                fail(f"the model job's settings shown differ (wanted, shown): {wrong}")
            px = wait("the model's written frame", 20,
                      lambda: (lambda x: x if x and x[5] else None)(p.preview_pixels()))
            with open(os.path.join(a.out, "model.rgba"), "wb") as f:
                f.write(px[2])
            with open(os.path.join(a.out, "model.json"), "w") as f:
                json.dump({"job": job4, "width": px[0], "height": px[1]}, f)
            shot(p, "job-model.png")
            step(f"the model's frame shown, {px[0]}x{px[1]}")

        # -- a phone-width look at the jobs page ------------------------------
        p.d.set_window_size(390, 844)
        p.go(f"{a.http}/#/jobs")
        wait("the jobs cards", 10, lambda: p.css(f'tr[data-job="{job}"]'))
        overflow = p.js("return document.documentElement.scrollWidth - window.innerWidth")
        if overflow > 1:
            fail(f"the jobs page is {overflow} px wider than a phone's screen")
        shot(p, "jobs-phone.png")
        step("phone width: no horizontal scrolling")
        # -- dark system theme -------------------------------------------------
        p.d.set_window_size(1280, 1000)
        light = p.js("return getComputedStyle(document.body).backgroundColor")
        if a.browser == "chromium":
            logs = [e for e in p.d.get_log("browser") if e.get("level") == "SEVERE"]
            # The refusals this script asked for (401) and a frame asked for while
            # being written (503) are expected; anything else is a fault of the page.
            bad = [e for e in logs if not any(c in e.get("message", "") for c in (" 401 ", " 503 "))]
            if bad:
                fail(f"errors in the browser console: {bad}")
        # Firefox gives WebDriver no console log: the page's own error
        # handler (window.onerror, unhandled rejections) is checked instead.
        errors = p.js("return window.__monitorErrors || []")
        if errors:
            fail(f"errors in the page: {errors}")
    finally:
        p.quit()

    # -- dark system theme, in a browser started with it --------------------
    p = Page(a.browser, a.binary, a.driver, 1280, 1000, dark=True)
    try:
        p.go(a.http + "/")
        wait("the sign-in form", 10, lambda: p.css("#token"))
        p.css("#token")[0].send_keys(a.token)
        p.click("#login-form button")
        wait("the jobs page", 15, lambda: p.css("#jobs"))
        p.go(f"{a.http}/#/jobs/{job}")
        wait("the job page", 10, lambda: p.attr("#job-state", "data-state") == "done")
        wait("the preview", 10, lambda: p.attr("#preview", "data-written") == "1")
        dark = p.js("return getComputedStyle(document.body).backgroundColor")
        if dark == light:
            fail(f"the page ignores a dark system theme (background {dark})")
        shot(p, "job-dark.png")
        step(f"dark theme: background {light} -> {dark}")
        errors = p.js("return window.__monitorErrors || []")
        if errors:
            fail(f"errors in the page: {errors}")
        step("OK")
    finally:
        p.quit()


if __name__ == "__main__":
    main()

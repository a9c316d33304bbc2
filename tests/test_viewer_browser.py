"""End-to-end: ``ns-viewer`` on a trained VoteSplat checkpoint, opened in headless Chromium.

The page is driven through the Chrome DevTools protocol (``--remote-debugging-port``) with the
``websockets`` client that viser already depends on, so no browser-automation package is needed.
The test waits for the first render, saves screenshots under ``tests/artifacts/`` (git-ignored),
checks that the "Output type" dropdown lists the VoteSplat outputs, switches to the instance
overlay and waits until the viewer reports the instances it computed for it.
"""

from __future__ import annotations

import base64
import itertools
import json
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from votesplat_ns.core.ply_io import read_gaussian_ply
from votesplat_ns.ns.viewer_render import DISPLAY_ISOLATE, OUTPUT_OVERLAY, VIEWER_OUTPUTS

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
VIEWER_START_TIMEOUT_S = 240
FIRST_RENDER_TIMEOUT_S = 240
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--remote-debugging-port=0",
    "--window-size=1280,800",
)

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install -y chromium)")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(
    condition, timeout_s: float, what: str, process: subprocess.Popen = None, log: Path = None, poll_s: float = 0.5
):
    """Poll ``condition()`` until it returns a truthy value; fail with the server log if it never does."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        if process is not None and process.poll() is not None:
            break
        time.sleep(poll_s)
    tail = log.read_text(errors="replace")[-4000:] if log is not None and log.exists() else ""
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}\n{tail}")


def page_served(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return b"<html" in response.read(4096).lower()
    except (urllib.error.URLError, ConnectionError, OSError):
        return False


class DevToolsPage:
    """The minimum of the Chrome DevTools protocol this test needs: one page, commands, JS evaluation."""

    def __init__(self, browser_ws_url: str) -> None:
        from websockets.sync.client import connect

        port = re.search(r":(\d+)/", browser_ws_url).group(1)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as response:
            targets = json.load(response)
        page = next(t for t in targets if t["type"] == "page")
        self.socket = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=30)
        self.ids = itertools.count(1)

    def call(self, method: str, **params):
        message_id = next(self.ids)
        self.socket.send(json.dumps({"id": message_id, "method": method, "params": params}))
        while True:  # skip events until our answer
            message = json.loads(self.socket.recv(timeout=120))
            if message.get("id") == message_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def js(self, expression: str):
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"JS error in {expression[:80]!r}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def click(self, x: float, y: float) -> None:
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)

    def screenshot(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))

    def close(self) -> None:
        self.socket.close()


# Viser draws each GUI input as a row: a <label> with the element's name, then the Mantine input
# (the label's "for" does not always match the input's id, so take the row's first input). A
# dropdown's input points at its option list with aria-controls (rendered once it has been opened).
_INPUT_OF_LABEL = """(label => {
  const l = Array.from(document.querySelectorAll('label')).find(e => e.innerText.trim() === label);
  if (!l) return null;
  let row = l.parentElement;
  while (row && !row.querySelector('input')) row = row.parentElement;
  const input = row && row.querySelector('input');
  if (!input) return null;
  input.scrollIntoView({block: 'center'});  // the control panel scrolls; clicks need it on screen
  const r = input.getBoundingClientRect();
  return {value: input.value, checked: input.checked, x: r.x + r.width / 2, y: r.y + r.height / 2, listbox: input.getAttribute('aria-controls')};
})"""
_OPTIONS_OF_LISTBOX = """(id => {
  const box = id && document.getElementById(id);
  const options = box ? box.querySelectorAll('[role=option]') : [];
  return Array.from(options).map(o => {
    const r = o.getBoundingClientRect();
    return {text: o.innerText.trim(), x: r.x + r.width / 2, y: r.y + r.height / 2};
  });
})"""


def gui_input(page: DevToolsPage, label: str) -> dict:
    """Value, checked state, centre and option list id of the GUI input labelled ``label``."""
    found = page.js(f"{_INPUT_OF_LABEL}({json.dumps(label)})")
    assert found is not None, f"the viewer page has no GUI input labelled {label!r}"
    return found


def open_dropdown(page: DevToolsPage, label: str) -> list:
    """Click the dropdown labelled ``label`` open; returns its options (text and centre)."""
    dropdown = gui_input(page, label)
    page.click(dropdown["x"], dropdown["y"])
    # The input names its option list (aria-controls) once it is open.
    return wait_for(
        lambda: page.js(f"{_OPTIONS_OF_LISTBOX}({json.dumps(gui_input(page, label)['listbox'])})"),
        30,
        f"the options of {label!r}",
    )


def rendered_resolution(page: DevToolsPage):
    """The "Resolution: WxHpx" the viewer shows after each render (0x0px before the first)."""
    text = page.js("document.body ? document.body.innerText : ''") or ""
    found = re.findall(r"Resolution: (\d+)x(\d+)px", text)
    return found[-1] if found and found[-1] != ("0", "0") else None


def settle_full_resolution(page: DevToolsPage, timeout_s: float = 60.0) -> None:
    """Give the viewer time to follow its quick low-resolution frames with a full one (for the screenshots).

    A still camera is rendered with its longer side at the "Max res" setting.
    """
    time.sleep(2.0)
    max_res = round(float(gui_input(page, "Max res")["value"]))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        resolution = rendered_resolution(page)
        if resolution is not None and max(int(resolution[0]), int(resolution[1])) == max_res:
            return
        time.sleep(0.5)


def test_ns_viewer_shows_the_instance_outputs_in_a_browser(trained_demo, tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    viewer_log = tmp_path / "ns_viewer.log"
    ns_viewer = Path(sys.executable).with_name("ns-viewer")
    command = [str(ns_viewer), "--load-config", str(trained_demo), "--viewer.websocket-port", str(port)]
    with open(viewer_log, "w") as log_handle:
        server = subprocess.Popen(command, stdout=log_handle, stderr=subprocess.STDOUT, cwd=tmp_path)
    browser = None
    page = None
    try:
        wait_for(lambda: page_served(url), VIEWER_START_TIMEOUT_S, "ns-viewer to serve its page", server, viewer_log)

        profile = tmp_path / "chromium-profile"
        profile.mkdir()
        browser_log = tmp_path / "chromium.log"
        with open(browser_log, "w") as log_handle:
            browser = subprocess.Popen(
                [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                stdout=subprocess.DEVNULL,
                stderr=log_handle,
            )
        # Chromium announces its DevTools endpoint on stderr.
        devtools = wait_for(
            lambda: re.search(r"DevTools listening on (ws://\S+)", browser_log.read_text(errors="replace")),
            60,
            "headless chromium's DevTools endpoint",
            browser,
            browser_log,
        )
        page = DevToolsPage(devtools.group(1))
        page.call("Page.enable")
        page.call("Page.navigate", url=url)

        resolution = wait_for(
            lambda: rendered_resolution(page), FIRST_RENDER_TIMEOUT_S, "the first render", server, viewer_log
        )
        assert int(resolution[0]) > 0 and int(resolution[1]) > 0
        settle_full_resolution(page)
        page.screenshot(ARTIFACTS / "viewer_first_render.png")
        body = page.js("document.body.innerText")
        assert "Connected" in body and "Output type" in body and "Instance level" in body, body[:2000]

        assert gui_input(page, "Output type")["value"] == "rgb"
        options = open_dropdown(page, "Output type")
        listed = [option["text"] for option in options]
        assert "rgb" in listed and all(name in listed for name in VIEWER_OUTPUTS), listed

        overlay = next(option for option in options if option["text"] == OUTPUT_OVERLAY)
        page.click(overlay["x"], overlay["y"])
        wait_for(lambda: gui_input(page, "Output type")["value"] == OUTPUT_OVERLAY, 30, "the overlay to be chosen")
        status = wait_for(
            lambda: re.search(r"(\d+) instances at level", gui_input(page, "Status")["value"] or ""),
            FIRST_RENDER_TIMEOUT_S,
            "the viewer to compute the instances for the overlay",
            server,
            viewer_log,
        )
        settle_full_resolution(page)
        page.screenshot(ARTIFACTS / "viewer_instance_overlay.png")
        assert int(status.group(1)) >= 0

        # Click-to-select: turn the mode on, click the render (a grid of points left of the
        # control panel, until one lands on an instance) and wait for the viewer to resolve each
        # click against that frame's instance-id render.
        click_mode = gui_input(page, "Click to select")
        page.click(click_mode["x"], click_mode["y"])
        wait_for(lambda: gui_input(page, "Click to select")["checked"], 30, "click mode to turn on")
        canvas = page.js(
            "(() => { const r = document.querySelector('canvas').getBoundingClientRect(); "
            "return {x: r.x, y: r.y, width: r.width, height: r.height}; })()"
        )
        points = [(0.5, 0.5)] + [(fx, fy) for fy in (0.3, 0.5, 0.7, 0.85) for fx in (0.1, 0.25, 0.4, 0.55, 0.7)]
        status = ""
        for fx, fy in points:
            x, y = canvas["x"] + fx * canvas["width"], canvas["y"] + fy * canvas["height"]
            before, last_click = gui_input(page, "Status")["value"], [0.0]

            def click_resolved():
                # A click reaches the server only once the server has registered its pointer
                # callback with the page (after any render holding the viewer lock): click again
                # at the same point until the status answers.
                now = gui_input(page, "Status")["value"]
                if now != before and re.search(r"selected instance \d+|clicked the background", now):
                    return now
                if time.monotonic() - last_click[0] > 5.0:
                    page.click(x, y)
                    last_click[0] = time.monotonic()
                return None

            status = wait_for(
                click_resolved,
                FIRST_RENDER_TIMEOUT_S,
                f"the click at {fx:.2f}, {fy:.2f} to be resolved",
                server,
                viewer_log,
            )
            if status.startswith("selected instance"):
                break
        picked = re.match(r"selected instance (\d+)", status)
        assert picked, f"no click on the demo scene's render landed on an instance: {status}"
        settle_full_resolution(page)
        page.screenshot(ARTIFACTS / "viewer_after_click.png")
        wait_for(
            lambda: gui_input(page, "Selected instance")["value"] == picked.group(1), 30, "the selected id in the GUI"
        )

        modes = open_dropdown(page, "Selected instance display")
        isolate = next(option for option in modes if option["text"] == DISPLAY_ISOLATE)
        page.click(isolate["x"], isolate["y"])
        wait_for(
            lambda: gui_input(page, "Selected instance display")["value"] == DISPLAY_ISOLATE, 30, "isolate to be chosen"
        )
        settle_full_resolution(page)
        page.screenshot(ARTIFACTS / "viewer_isolated.png")

        # Export the selected instance: a standard 3DGS PLY next to the run's config.
        export = page.js("""(() => {
          const b = Array.from(document.querySelectorAll('button')).find(e => e.innerText.trim() === 'Export selected instance (PLY)');
          b.scrollIntoView({block: 'center'});
          const r = b.getBoundingClientRect();
          return {x: r.x + r.width / 2, y: r.y + r.height / 2};
        })()""")
        page.click(export["x"], export["y"])
        wrote = wait_for(
            lambda: re.match(r"wrote (.+\.ply) \((\d+) Gaussians\)", gui_input(page, "Status")["value"]),
            60,
            "the export",
        )
        exported = read_gaussian_ply(wrote.group(1))
        assert Path(wrote.group(1)).parent.parent == Path(trained_demo).resolve().parent
        assert exported["means"].shape[0] == int(wrote.group(2)) > 0
        assert server.poll() is None, "ns-viewer exited"
        assert "Traceback" not in viewer_log.read_text(errors="replace"), viewer_log.read_text(errors="replace")[-4000:]
    finally:
        if page is not None:
            page.close()
        for process in (browser, server):
            if process is not None and process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
        if viewer_log.exists():
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(viewer_log, ARTIFACTS / "ns_viewer.log")

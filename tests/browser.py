"""Open an HTML map in Debian's headless Chromium with networking off and report what the page holds.

The page is copied with two scripts added: one first in <head> that records uncaught errors, failed
resource loads and console.error/warn calls, and one that, after load, writes a JSON summary into the
DOM (the Leaflet map, each overlay of the layer switcher with its feature count, on/off switching, the
resources the page fetched); ``--dump-dom`` prints it. Chromium's own console log (stderr) is kept too.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WINDOW = "1200,900"

_CAPTURE = """<script>
window.__errors = [];
window.addEventListener("error", e => __errors.push("error: " + (e.message || (e.target && (e.target.src || e.target.href)) || e.type)), true);
window.addEventListener("unhandledrejection", e => __errors.push("rejection: " + e.reason));
for (const level of ["error", "warn"]) {
  const original = console[level];
  console[level] = function (...args) { __errors.push(level + ": " + args.map(String).join(" ")); original.apply(console, args); };
}
</script>"""

_PROBE = """<script>
window.addEventListener("load", () => setTimeout(() => {
  const names = Object.keys(window).filter(k => { try { return window[k] instanceof L.Map; } catch (e) { return false; } });
  const map = names.length ? window[names[0]] : null;
  const overlays = [];
  for (const label of document.querySelectorAll(".leaflet-control-layers-overlays label")) {
    const input = label.querySelector("input");
    const layer = map && map._layers[input.layerId];
    const entry = {name: label.textContent.trim(), checked: input.checked, on_map: Boolean(layer)};
    if (layer) {
      entry.kind = layer instanceof L.ImageOverlay ? "image" : "features";
      if (layer.getLayers) entry.count = layer.getLayers().length;
      if (layer instanceof L.ImageOverlay) entry.loaded = layer._image.complete && layer._image.naturalWidth > 0;
      input.click();
      entry.off_after_click = !map.hasLayer(layer);
      input.click();
      entry.on_after_second_click = map.hasLayer(layer);
    }
    overlays.push(entry);
  }
  const result = {
    maps: names.length, overlays: overlays, errors: window.__errors,
    paths: document.querySelectorAll(".leaflet-overlay-pane path").length,
    legend: document.querySelectorAll(".map-legend svg").length,
    resources: performance.getEntriesByType("resource").map(e => e.name).filter(n => !n.startsWith("data:")),
  };
  const pre = document.createElement("pre");
  pre.id = "probe";
  pre.textContent = JSON.stringify(result);
  document.body.appendChild(pre);
}, 0));
</script>"""


def require_chromium() -> str:
    """The Chromium binary; skip without it (fail when CI=true: the browser test must run in CI)."""
    if CHROMIUM is None:
        msg = "chromium not installed (apt-get install chromium; make setup installs it)"
        if os.environ.get("CI") == "true":
            pytest.fail(msg + " (CI=true: the browser test must run)")
        pytest.skip(msg)
    return CHROMIUM


def _offline_prefix() -> list[str]:
    """``unshare -n`` (no network interface at all) where this user may, else nothing (the flags still
    point every host name and proxy nowhere)."""
    unshare = shutil.which("unshare")
    if unshare and subprocess.run([unshare, "-n", "true"], capture_output=True).returncode == 0:
        return [unshare, "-n"]
    return []


def _chromium(url: str, *flags: str) -> subprocess.CompletedProcess:
    cmd = [*_offline_prefix(), require_chromium(), "--headless", "--no-sandbox", "--disable-gpu",
           "--disable-dev-shm-usage", "--no-first-run", "--host-resolver-rules=MAP * ~NOTFOUND",
           "--proxy-server=127.0.0.1:9", "--enable-logging=stderr", "--v=0", f"--window-size={WINDOW}",
           "--virtual-time-budget=10000", *flags, url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def probe(html: Path, work: Path) -> dict:
    """Open a copy of ``html`` with the probe scripts offline; returns the probe's JSON plus
    ``console``: Chromium's console lines from stderr for the page."""
    text = html.read_text(encoding="utf-8")
    probed = work / f"probed_{html.name}"
    probed.write_text(text.replace("<head>", "<head>" + _CAPTURE, 1).replace("</body>", _PROBE + "</body>", 1),
                      encoding="utf-8")
    run = _chromium(probed.as_uri(), "--dump-dom")
    found = re.search(r'<pre id="probe">(.*?)</pre>', run.stdout, re.S)
    assert found, f"no probe output from chromium (rc {run.returncode}):\n{run.stderr[-3000:]}"
    result = json.loads(found.group(1).replace("&lt;", "<").replace("&gt;", ">").replace("&amp;", "&"))
    # Chromium's own chrome:// pages log too (e.g. "Slow network is detected"); keep the map page's lines
    result["console"] = [line for line in run.stderr.splitlines() if ":CONSOLE" in line and "source: file:" in line]
    return result


def screenshot(html: Path, png: Path) -> Path:
    """A PNG of ``html`` as headless Chromium draws it offline at WINDOW pixels."""
    run = _chromium(html.resolve().as_uri(), f"--screenshot={png.resolve()}")
    assert png.exists() and png.stat().st_size > 0, f"no screenshot (rc {run.returncode}):\n{run.stderr[-3000:]}"
    return png


def geojson_layers(html: Path) -> list[dict]:
    """The GeoJSON FeatureCollections a folium map embeds, in the order they were added."""
    text = html.read_text(encoding="utf-8")
    return [json.loads(m.group(1)) for m in re.finditer(r"geo_json_\w+_add\((\{.*?\})\);\n", text)]


def image_overlay(html: Path) -> tuple[np.ndarray, list[list[float]]]:
    """The first image overlay of a folium map: RGBA pixels (H, W, 4) in 0..1 and [[south, west], [north, east]]."""
    import io

    import matplotlib.image

    text = html.read_text(encoding="utf-8")
    found = re.search(r'L\.imageOverlay\(\s*"data:image/png;base64,([^"]+)",\s*(\[\[.*?\]\])', text, re.S)
    assert found, "no image overlay in the map"
    pixels = matplotlib.image.imread(io.BytesIO(base64.b64decode(found.group(1))), format="png")
    return pixels, json.loads(found.group(2))


if __name__ == "__main__":  # python -m tests.browser MAP.html SHOT.png: the README's screenshot
    import sys

    screenshot(Path(sys.argv[1]), Path(sys.argv[2]))

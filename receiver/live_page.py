"""The live view's page: the picture (an MJPEG stream in an ``<img>``) and the call's figures
beside it, polled from ``figures.json`` twice a second. Plain HTML and JavaScript, no
framework, for current Chromium and Firefox.

Element ids the tests read: ``picture``, ``status``, ``fps``, ``latency``, ``frames``,
``size`` and, per channel, ``kbps-NAME`` (``kbps-total`` for the sum).
"""

from __future__ import annotations

#: Channels listed first, in this order (others follow as they appear).
CHANNELS = ("geometry", "rem", "snapshot", "control")

PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>facewire live view</title>
<style>
  body { margin: 0; padding: 16px; background: #1d1f21; color: #e8e8e8;
         font: 15px/1.4 system-ui, sans-serif; }
  main { display: flex; flex-wrap: wrap; gap: 16px; align-items: flex-start; }
  #picture { display: block; max-width: min(100%, 1280px); height: auto; background: #000;
             min-width: 320px; min-height: 240px; }
  aside { min-width: 260px; max-width: 360px; }
  #sound { text-align: left; font-size: 13px; color: #a0a0a0; }
  h1 { font-size: 17px; margin: 0 0 8px; }
  #status { margin: 0 0 12px; color: #b5bd68; }
  table { border-collapse: collapse; }
  th { text-align: left; font-weight: normal; color: #a0a0a0; padding: 2px 16px 2px 0;
       white-space: nowrap; vertical-align: top; }
  td { text-align: right; font-variant-numeric: tabular-nums; padding: 2px 0; }
  tr.sum th, tr.sum td { border-top: 1px solid #555; }
  .gap th { padding-top: 12px; }
</style>
</head>
<body>
<main>
  <img id="picture" src="stream.mjpg" alt="the live picture">
  <aside>
    <h1>facewire: live view</h1>
    <p id="status">connecting&hellip;</p>
    <table>
      <tr><th>pictures per second</th><td id="fps">&ndash;</td></tr>
      <tr><th>latency, capture to screen</th><td id="latency">&ndash;</td></tr>
      <tr><th>frames</th><td id="frames">&ndash;</td></tr>
      <tr><th>size</th><td id="size">&ndash;</td></tr>
      <tr><th>sound</th><td id="sound">not in this page (an MJPEG stream carries none): it
        plays on the receiver's sound device and goes into its --record file</td></tr>
      <tbody id="kbps"><tr class="gap"><th>kbit/s received</th><td></td></tr></tbody>
    </table>
  </aside>
</main>
<script>
"use strict";
const ORDER = __CHANNELS__;
const $ = (id) => document.getElementById(id);
const NOT_IN_PAGE = "not in this page either (an MJPEG stream carries none)";

function channelCell(name) {
  let cell = $("kbps-" + name);
  if (!cell) {
    const row = document.createElement("tr");
    if (name === "total") row.className = "sum";
    const th = document.createElement("th");
    th.textContent = name;
    cell = document.createElement("td");
    cell.id = "kbps-" + name;
    row.append(th, cell);
    $("kbps").append(row);
  }
  return cell;
}

function show(f) {
  $("fps").textContent = f.fps.toFixed(1);
  $("latency").textContent = f.latency_ms === null ? "n/a (two clocks)"
    : f.latency_ms.p50.toFixed(1) + " ms";
  $("frames").textContent = String(f.frames);
  $("size").textContent = f.session ? f.session.width + "\\u00d7" + f.session.height : "\\u2013";
  const names = Object.keys(f.kbps).filter((n) => n !== "total");
  names.sort((a, b) => (ORDER.indexOf(a) + 1 || 99) - (ORDER.indexOf(b) + 1 || 99));
  for (const name of [...names, "total"]) {
    if (name in f.kbps) channelCell(name).textContent = f.kbps[name].toFixed(2);
  }
  // The sound's own line (receiver/audio.py) belongs beside the sound, not in the status.
  const aboutSound = (e) => e.startsWith("no sound device");
  const heard = f.events.filter(aboutSound);
  if (heard.length) $("sound").textContent = heard[heard.length - 1] + "; " + NOT_IN_PAGE;
  const said = f.events.filter((e) => !aboutSound(e));
  let status = said.length ? said[said.length - 1] : "waiting for a sender";
  if (f.age_s !== null && f.age_s > 2) {
    status += " (no new picture for " + Math.round(f.age_s) + " s)";
  }
  $("status").textContent = status;
}

async function poll() {
  try {
    const r = await fetch("figures.json", { cache: "no-store" });
    show(await r.json());
  } catch (e) {
    $("status").textContent = "the receiver is not answering";
  }
  setTimeout(poll, 500);
}

// A stream that broke (the receiver restarted) is opened again.
$("picture").addEventListener("error", () => {
  setTimeout(() => { $("picture").src = "stream.mjpg?t=" + Date.now(); }, 1000);
});
poll();
</script>
</body>
</html>
"""


def page() -> str:
    """The page's HTML."""
    channels = "[" + ", ".join(f'"{c}"' for c in CHANNELS) + "]"
    return PAGE.replace("__CHANNELS__", channels)

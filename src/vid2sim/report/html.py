"""HTML building blocks of the report: escaping, number formatting, tables, and the page around them.

The page is one self-contained ``index.html``: its style sheet and its small script are inline, every
picture and video is a relative ``media/…`` path, nothing is fetched from the network, so the folder opens
from ``file://`` and can be zipped or moved as it is.

Numbers in tables carry their full-precision value in a ``data-value`` attribute (the text shows it
rounded), so a reader — or a test — can check a table against ``evaluation.json``.

The script (no dependencies) drives the videos together — play/pause, speed, and a frame slider that seeks
all of them to one frame; ``index.html#frame=16`` opens the page paused on frame 16 — and reports in the
root element's ``data-*`` attributes how many videos and images the browser loaded and where they were laid
out (``data-videos-ready``, ``data-images-ready``, ``data-layout``); the browser test reads those.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

from vid2sim.report.config import FUTURE_COLOUR, OBSERVED_COLOUR


def esc(text: Any) -> str:
    """HTML-escaped ``str(text)``."""
    return html.escape(str(text), quote=True)


def fmt(value: Any, digits: int = 2, unit: str = "") -> str:
    """A number with ``digits`` decimals (``—`` for None / NaN / non-numbers), with an optional unit."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return "—"
    return f"{value:.{digits}f}" + (f" {unit}" if unit else "")


def fmt_sci(value: Any, digits: int = 3) -> str:
    """A number in scientific notation with ``digits`` significant digits, e.g. ``1.02e+05`` → ``1.02 × 10⁵``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value == 0:
        return fmt(value, digits)
    exponent = math.floor(math.log10(abs(value)))
    mantissa = value / 10 ** exponent
    if round(abs(mantissa), digits - 1) >= 10:
        mantissa, exponent = mantissa / 10, exponent + 1
    sup = str(exponent).translate(str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹"))
    return f"{mantissa:.{digits - 1}f} × 10{sup}"


def _data(value: Any, key: str) -> str:
    has = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    metric = f' data-metric="{esc(key)}"' if key else ""
    return f'{metric} data-value="{repr(float(value)) if has else ""}"'


def num_cell(value: Any, text: str | None = None, digits: int = 2, cls: str = "num", key: str = "") -> str:
    """A ``<td>`` showing ``text`` (default: ``value`` with ``digits`` decimals) with ``data-value`` holding
    the full-precision value (``repr``; empty when there is no number) and, with ``key``, ``data-metric``
    naming it (e.g. ``dynamic.psnr``)."""
    shown = fmt(value, digits) if text is None else text
    return f'<td class="{cls}"{_data(value, key)}>{esc(shown)}</td>'


def num_span(value: Any, text: str | None = None, digits: int = 2, key: str = "") -> str:
    """Like :func:`num_cell`, as a ``<span>`` (several values in one cell)."""
    shown = fmt(value, digits) if text is None else text
    return f'<span class="v"{_data(value, key)}>{esc(shown)}</span>'


def table(headers: Sequence[str], rows: Sequence[str], table_id: str = "", cls: str = "",
          foot: Sequence[str] = ()) -> str:
    """A table; ``headers`` are (already escaped) header HTML strings, ``rows`` and ``foot`` are ``<td>…``
    strings for one row each."""
    ident = f' id="{esc(table_id)}"' if table_id else ""
    head = "".join(f"<th>{h}</th>" for h in headers)
    body = "".join(f"<tr>{r}</tr>" for r in rows)
    tfoot = f"<tfoot>{''.join(f'<tr>{r}</tr>' for r in foot)}</tfoot>" if foot else ""
    return (f'<div class="table-wrap"><table{ident} class="{esc(cls)}"><thead><tr>{head}</tr></thead>'
            f"<tbody>{body}</tbody>{tfoot}</table></div>")


def section(ident: str, title: str, body: str, intro: str = "") -> str:
    """A ``<section>`` with an anchor, a heading and an optional introduction paragraph (HTML)."""
    lead = f'<p class="intro">{intro}</p>' if intro else ""
    return f'<section id="{esc(ident)}"><h2>{esc(title)}</h2>{lead}{body}</section>'


def card(label: str, value: str, note: str = "", tone: str = "", unit: str = "") -> str:
    """A summary figure: a big value (with a smaller unit) under a label, over a small note; ``tone`` "good"
    or "bad" colours the value."""
    u = f'<span class="unit">{esc(unit)}</span>' if unit else ""
    return (f'<div class="card {esc(tone)}"><div class="card-label">{esc(label)}</div>'
            f'<div class="card-value">{esc(value)}{u}</div><div class="card-note">{esc(note)}</div></div>')


CSS = """
:root { --fg:#1b1f24; --muted:#5b6572; --line:#d8dde3; --bg:#f6f7f9; --card:#fff; --accent:#1f4e9c;
        --obs:%(obs)s; --fut:%(fut)s; --bad:#b42318; --good:#1f7a4d; }
* { box-sizing: border-box; }
html { scroll-behavior: smooth; }
body { margin:0; font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color:var(--fg); background:var(--bg); }
header.top { background:#1f2328; color:#f0f2f5; padding:22px 32px 12px; }
header.top h1 { margin:0; font-size:24px; font-weight:650; letter-spacing:.2px; }
header.top .sub { margin:4px 0 0; color:#aab3bf; font-size:14px; }
header.top .sub b { color:#e6e9ee; font-weight:600; }
nav { display:flex; gap:4px; flex-wrap:wrap; position:sticky; top:0; z-index:5; background:#1f2328;
      padding:0 28px 10px; }
nav a { color:#cfd6df; text-decoration:none; font-size:13.5px; padding:5px 10px; border-radius:6px; }
nav a:hover { background:#343a42; color:#fff; }
main { max-width:1260px; margin:0 auto; padding:8px 28px 40px; }
section { background:var(--card); border:1px solid var(--line); border-radius:10px; padding:18px 22px 20px;
          margin:18px 0; }
h2 { margin:0 0 10px; font-size:19px; }
h3 { margin:16px 0 8px; font-size:15.5px; }
p.intro, .note { color:var(--muted); margin:0 0 12px; font-size:14px; }
.cards { display:grid; grid-template-columns:repeat(auto-fill, minmax(190px, 1fr)); gap:12px; }
.card { border:1px solid var(--line); border-radius:9px; padding:10px 14px; background:#fbfcfd; }
.card-label { font-size:13px; color:var(--muted); font-weight:600; }
.card-value { font-size:25px; font-weight:650; font-variant-numeric:tabular-nums; white-space:nowrap; }
.card-value .unit { font-size:15px; font-weight:500; color:var(--muted); margin-left:3px; }
.card-note { font-size:12.5px; color:var(--muted); }
.card.good .card-value { color:var(--good); } .card.bad .card-value { color:var(--bad); }
.table-wrap { overflow-x:auto; }
table { border-collapse:collapse; font-size:14px; min-width:50%%; }
th, td { padding:6px 12px; border-bottom:1px solid var(--line); text-align:left; vertical-align:middle; }
th { background:#eef1f4; font-weight:600; font-size:13px; }
tbody tr:nth-child(even) { background:#fafbfc; }
tfoot td { font-weight:650; border-top:2px solid #aab3bf; background:#f3f5f8; }
td.num { text-align:right; font-variant-numeric:tabular-nums; white-space:nowrap; }
td.na { color:#9aa3ad; }
.status { display:inline-block; padding:1px 9px; border-radius:10px; font-size:12.5px; font-weight:600; color:#fff; }
.status.ok { background:var(--good); } .status.failed { background:var(--bad); }
.error-text { color:var(--bad); font-size:12.5px; max-width:360px; white-space:pre-wrap; }
.tag { display:inline-block; padding:0 8px; border-radius:9px; font-size:12px; font-weight:600; color:#fff; }
.tag.obs { background:var(--obs); } .tag.fut { background:var(--fut); } .tag.novel { background:#7a5af8; }
.controls { display:flex; gap:14px; align-items:center; flex-wrap:wrap; margin:4px 0 14px; padding:10px 14px;
            background:#f3f5f8; border-radius:8px; font-size:14px; }
.controls button { font:inherit; padding:4px 14px; border-radius:6px; border:1px solid #aab3bf;
                   background:#fff; cursor:pointer; }
.controls input[type=range] { width:260px; }
.controls .legend img { height:18px; vertical-align:middle; }
.video-grid { display:grid; grid-template-columns:repeat(auto-fill, minmax(560px, 1fr)); gap:16px; }
.video-card { border:1px solid var(--line); border-radius:9px; overflow:hidden; background:#1f2328; }
.video-card .caption { background:#fff; padding:7px 12px; display:flex; justify-content:space-between;
                       align-items:center; gap:8px; flex-wrap:wrap; font-size:14px; }
.video-card .caption b { font-size:15px; }
.video-card .caption .crop { color:var(--muted); font-size:12.5px; margin-left:4px; }
.video-card video, .video-card img.anim { display:block; width:100%%; height:auto; }
.figure { margin:6px 0 4px; } .figure img { max-width:100%%; height:auto; display:block; }
.figure.strip img { border-radius:6px; }
.gifs { display:flex; flex-wrap:wrap; gap:10px; } .gifs figure { margin:0; } .gifs img { width:256px; height:auto;
image-rendering:auto; border-radius:6px; }
.gifs figcaption { font-size:12px; color:#555; text-align:center; }
.bar { height:10px; background:var(--accent); border-radius:3px; min-width:2px; }
.thumb { border-radius:4px; display:block; height:132px; width:auto; }
body.wide main { max-width:1500px; }
td .sub { display:block; color:var(--muted); font-size:12.5px; }
td.pair { text-align:right; font-variant-numeric:tabular-nums; white-space:nowrap; line-height:1.35; }
td.pair .v { display:block; } td.pair .v + .v { color:var(--muted); font-size:12.5px; }
td.material .v { display:block; } td.material .lbl { color:var(--muted); font-size:12px; margin-right:4px; }
a { color:var(--accent); }
code { font-size:13px; background:#eef1f4; padding:1px 5px; border-radius:4px; }
pre { background:#1f2328; color:#e6e9ee; padding:10px 14px; border-radius:8px; overflow-x:auto; font-size:13px; }
footer { color:var(--muted); font-size:13px; text-align:center; padding:10px 0 30px; }
""" % {"obs": OBSERVED_COLOUR, "fut": FUTURE_COLOUR}

SCRIPT = r"""
(function () {
  const vids = Array.from(document.querySelectorAll('video.sync'));
  const root = document.documentElement;
  const slider = document.getElementById('frame-slider');
  const label = document.getElementById('frame-label');
  const playBtn = document.getElementById('play-toggle');
  const speed = document.getElementById('speed');
  function setRate() { const r = speed ? parseFloat(speed.value) : 1; vids.forEach(v => { v.playbackRate = r; }); }
  function playing() { return vids.some(v => !v.paused); }
  if (playBtn) playBtn.addEventListener('click', () => {
    if (playing()) { vids.forEach(v => v.pause()); playBtn.textContent = 'Play'; }
    else { const t = vids.length ? vids[0].currentTime : 0;
           vids.forEach(v => { v.currentTime = t; v.play(); }); playBtn.textContent = 'Pause'; }
  });
  if (speed) speed.addEventListener('change', setRate);
  function seek(f) {
    vids.forEach(v => { v.pause(); v.currentTime = (f + 0.5) / parseFloat(v.dataset.fps); });
    if (playBtn) playBtn.textContent = 'Play';
    if (label) label.textContent = 'frame ' + f;
    if (slider) slider.value = f;
  }
  if (slider) slider.addEventListener('input', () => seek(parseInt(slider.value, 10)));
  const m = /frame=(\d+)/.exec(location.hash);  // index.html#frame=16 opens paused on frame 16
  if (m) { const f = parseInt(m[1], 10); vids.forEach(v => { v.autoplay = false; v.pause(); });
           vids.forEach(v => v.addEventListener('loadedmetadata', () => seek(f))); seek(f); }
  vids.forEach(v => v.addEventListener('timeupdate', () => {
    if (!slider || v !== vids[0] || v.paused) return;
    const f = Math.min(parseInt(slider.max, 10), Math.floor(v.currentTime * parseFloat(v.dataset.fps)));
    slider.value = f; if (label) label.textContent = 'frame ' + f;
  }));
  setRate();
  function report() {
    const imgs = Array.from(document.images);
    root.dataset.videos = vids.length;
    root.dataset.videosReady = vids.filter(v => v.readyState >= 2 && v.videoWidth > 0).length;
    root.dataset.videoSizes = JSON.stringify(vids.map(v => [v.videoWidth, v.videoHeight]));
    root.dataset.images = imgs.length;
    root.dataset.imagesReady = imgs.filter(i => i.complete && i.naturalWidth > 0).length;
    root.dataset.layout = JSON.stringify(Array.from(document.querySelectorAll('[data-probe]')).map(e => {
      const r = e.getBoundingClientRect();
      return [e.dataset.probe, Math.round(r.left + scrollX), Math.round(r.top + scrollY),
              Math.round(r.width), Math.round(r.height)];
    }));
  }
  vids.forEach(v => v.addEventListener('loadeddata', report));
  window.addEventListener('load', report);
  setInterval(report, 250);
  report();
})();
"""


def page(title: str, subtitle_html: str, nav: Sequence[tuple[str, str]], body: str, footer_html: str,
         body_class: str = "") -> str:
    """The whole ``index.html``: head with inline CSS, a dark header with title, subtitle and section links,
    the sections, a footer, and the inline script (``body_class`` "wide" widens the page)."""
    links = "".join(f'<a href="#{esc(anchor)}">{esc(label)}</a>' for anchor, label in nav)
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<meta name=\"generator\" content=\"vid2sim report\">\n<title>{esc(title)}</title>\n"
        f"<style>{CSS}</style>\n</head>\n<body class=\"{esc(body_class)}\">\n"
        f"<header class=\"top\"><h1>{esc(title)}</h1><p class=\"sub\">{subtitle_html}</p></header>\n"
        f"<nav>{links}</nav>\n<main>\n{body}\n</main>\n<footer>{footer_html}</footer>\n"
        f"<script>{SCRIPT}</script>\n</body>\n</html>\n"
    )

"""A self-contained interactive HTML report of a convergence run.

``write_html_report(path, result, scene=...)`` writes ONE file: every image
is embedded as a PNG ``data:`` URI, the viewer is a few hundred lines of
inline vanilla JavaScript and CSS, and the page loads nothing from the
network (no CDN, no web fonts).  One file survives being moved, mailed or
attached to an issue; the same PNGs are also written beside ``report.md``
(``images/``) for the Markdown report.

The page holds

* a metrics table of every method at the report budget (relative MSE with
  its ε, SMAPE with its ε, 1 − SSIM, FLIP when ``flip-evaluator`` is
  installed, RMSE, renderer / toolkit / wall time); a click on a row shows
  that method in the viewer, a click on a header sorts;
* a viewer: layer buttons (reference, box, every method) flipped with the
  keys 1..9, 0 (Shift + digit for layers 11..20), ← / → and Space (back
  to the previous layer), all at the same zoom and pan; wheel zoom about
  the cursor, drag to pan, nearest-neighbour pixels (CSS
  ``image-rendering: pixelated``), ``f`` fits the view again;
* an exposure slider (``+`` / ``-``): applied in the browser as a CSS
  ``filter: brightness(2^(EV/2.2))`` on the tone-mapped 8-bit sRGB PNGs.
  2.2 approximates the sRGB curve, so this mimics a linear exposure change
  of EV stops on the preview without embedding an image per stop; it
  cannot bring back highlights the PNG clipped at 1 (they were clipped at
  the report's base exposure, 0 EV);
* per method, the per-pixel relative squared error
  ``(img − ref)² / (ref² + ε)`` (mean over channels) in false colour
  (viridis, log scale 1e-5..1, black where the error is exactly 0), key
  ``e``; sample density of adaptive runs, key ``d``; the image, key ``i``;
* the convergence plots, and every point of the run in a folded table.
"""

from __future__ import annotations

import base64
import html
import json
import math
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from ..io import write_false_colour, write_png_preview
from ..core.metrics import relative_mse_map

__all__ = ["write_html_report", "report_layers", "METRIC_COLUMNS", "ERROR_MAP_RANGE"]

#: The log-scale range of the relative-squared-error maps (the same as report.md's).
ERROR_MAP_RANGE = (1e-5, 1.0)

#: (row key, header, number format) of the metric columns; FLIP only when the rows have it.
METRIC_COLUMNS = (
    ("relative_mse", "relMSE", "{:.4g}"),
    ("smape", "SMAPE", "{:.4g}"),
    ("one_minus_ssim", "1−SSIM", "{:.4g}"),
    ("flip", "FLIP", "{:.4g}"),
    ("rmse", "RMSE", "{:.4g}"),
)
TIME_COLUMNS = (
    ("renderer_seconds", "renderer s", "{:.3f}"),
    ("toolkit_seconds", "toolkit s", "{:.3f}"),
    ("wall_seconds", "wall s", "{:.3f}"),
)


def _data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _label(method: str, mode: str) -> str:
    return "box (noisy input)" if method == "input" else f"{method} ({mode})"


def report_layers(result) -> list[tuple[str, str, str]]:
    """The viewer's layers in key order: ``(layer id, label, method/mode key)``.

    Reference first, then the box image of the uniform samples (the noisy
    input: ``box (uniform)`` when box ran, else the ``input`` image), then
    every other image sorted by mode and method.
    """
    keys = sorted(result.images)
    box = ("box", "uniform") if ("box", "uniform") in result.images else (
        ("input", "uniform") if ("input", "uniform") in result.images else None)
    out = [("reference", "reference", None)]
    if box is not None:
        out.append((f"{box[0]}_{box[1]}", _label(*box) if box[0] == "input" else "box (uniform, noisy input)", box))
    rest = [k for k in keys if k != box and k[0] != "input"]
    rest.sort(key=lambda k: (k[1] != "uniform", k[0]))
    out += [(f"{m}_{md}", _label(m, md), (m, md)) for m, md in rest]
    return out


def _fmt(value, fmt):
    if value is None:
        return "—"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return html.escape(str(value))
    if not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return fmt.format(v)


def _table(rows, columns, *, layer_ids, best: bool, table_id: str) -> str:
    """An HTML table; ``best`` marks each metric column's minimum."""
    head = "".join(f'<th data-col="{i}">{html.escape(h)}</th>' for i, (_, h, _) in enumerate(columns))
    mins = {}
    if best:
        for key, _, _ in columns:
            if key in {k for k, _, _ in METRIC_COLUMNS}:
                vals = [float(r[key]) for r in rows if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
                if vals:
                    mins[key] = min(vals)
    body = []
    for r in rows:
        lid = f"{r['method']}_{r['mode']}"
        attr = f' data-layer="{html.escape(lid)}"' if lid in layer_ids else ""
        cells = []
        for key, _, fmt in columns:
            v = r.get(key)
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                cls = ' class="num best"' if key in mins and v == mins[key] else ' class="num"'
                sort = f' data-v="{float(v)!r}"'
                cells.append(f"<td{cls}{sort}>{_fmt(v, fmt)}</td>")
            else:
                cells.append(f"<td>{html.escape(str(v)) if v is not None else '—'}</td>")
        body.append(f"<tr{attr}>{''.join(cells)}</tr>")
    return (f'<table id="{table_id}" class="metrics"><thead><tr>{head}</tr></thead>'
            f"<tbody>{''.join(body)}</tbody></table>")


def write_html_report(path, result, *, scene: str, title: str | None = None,
                      plots: Sequence[str | Path] = (), notes: Sequence[str] = ()) -> Path:
    """Write the interactive report of a :class:`~mcrecon.experiments.convergence.ConvergenceResult`.

    Parameters
    ----------
    path : path-like
        The ``.html`` file to write (its folder is created).
    result : ConvergenceResult
        With its rows, images at ``report_spp``, density maps and reference.
    scene : str
        Named in the title.
    plots : sequence of path-like
        PNG figures embedded under the viewer (the convergence plots).
    notes : sequence of str
        Extra lines shown under the title.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ref = result.reference
    h, w = ref.shape[:2]
    eps = getattr(result, "eps", 0.01)
    smape_eps = getattr(result, "smape_eps", 0.01)
    lo, hi = ERROR_MAP_RANGE
    layers = []
    with tempfile.TemporaryDirectory(prefix="mcrecon-html-") as tmp:
        tmp = Path(tmp)
        for lid, label, key in report_layers(result):
            img = ref if key is None else result.images[key]
            write_png_preview(tmp / f"{lid}.png", img)
            layer = {"id": lid, "label": label, "image": _data_uri(tmp / f"{lid}.png"), "error": None,
                     "density": None, "density_max": None}
            if key is not None:
                err = relative_mse_map(img, ref, eps=eps)
                write_false_colour(tmp / f"{lid}_error.png", err, log=True, vmin=lo, vmax=hi)
                layer["error"] = _data_uri(tmp / f"{lid}_error.png")
                layer["error_mean"] = float(np.mean(err))
                if key in result.maps:
                    counts = np.asarray(result.maps[key], dtype=np.float64)
                    write_false_colour(tmp / f"{lid}_density.png", counts, vmin=0.0)
                    layer["density"] = _data_uri(tmp / f"{lid}_density.png")
                    layer["density_max"] = float(np.max(counts)) if counts.size else 0.0
            layers.append(layer)
    layer_ids = {la["id"] for la in layers}
    has_flip = any("flip" in r for r in result.rows)
    metric_cols = [c for c in METRIC_COLUMNS if c[0] != "flip" or has_flip]
    cols = [("method", "method", None), ("mode", "mode", None), ("spp", "spp", "{:.0f}"),
            ("samples", "samples", "{:.0f}"), *metric_cols, *TIME_COLUMNS]
    report_rows = sorted((r for r in result.rows if r["spp"] == result.report_spp),
                         key=lambda r: (r["mode"] != "uniform", r["method"]))
    all_rows = sorted(result.rows, key=lambda r: (r["method"], r["mode"], r["spp"]))
    why = "; ".join(n for n in getattr(result, "notes", []) if "FLIP" in n) or "FLIP was switched off"
    flip_note = ("FLIP: NVIDIA's HDR-FLIP (flip-evaluator), mean over pixels." if has_flip else
                 f"FLIP: not computed ({why}).")
    info = [f"{w}×{h} pixels; images and the first table at {result.report_spp} spp (average). "
            f"relMSE = mean (img − ref)² / (ref² + ε), ε = {eps:g}; "
            f"SMAPE = mean |img − ref| / (|img| + |ref| + ε), ε = {smape_eps:g}; "
            "1−SSIM on the sRGB previews; lower is better everywhere; the best value of each metric is bold.",
            flip_note, *notes]
    figures = "".join(f'<figure><img class="plot" alt="{html.escape(Path(p).stem)}" src="{_data_uri(p)}">'
                      f"<figcaption>{html.escape(Path(p).name)}</figcaption></figure>"
                      for p in plots if Path(p).exists())
    data = {"width": w, "height": h, "layers": layers, "error_range": [lo, hi], "eps": eps}
    data_json = json.dumps(data).replace("</", "<\\/")
    title = title or f"Convergence: {scene}"
    page = _PAGE.format(
        title=html.escape(title),
        info="".join(f"<p>{html.escape(line)}</p>" for line in info),
        table=_table(report_rows, cols, layer_ids=layer_ids, best=True, table_id="metrics"),
        all_table=_table(all_rows, cols, layer_ids=layer_ids, best=False, table_id="all-points"),
        n_points=len(all_rows),
        figures=figures,
        data=data_json,
        css=_CSS,
        js=_JS,
        lo=f"{lo:g}", hi=f"{hi:g}",
    )
    path.write_text(page, encoding="utf-8")
    return path


_CSS = """
:root { color-scheme: light dark; --bg: #fff; --fg: #111; --muted: #666; --line: #ccc; --hl: #2a6fdb; }
@media (prefers-color-scheme: dark) { :root { --bg: #161616; --fg: #e8e8e8; --muted: #999; --line: #444; } }
body { font: 14px/1.4 system-ui, sans-serif; margin: 1em 2em; background: var(--bg); color: var(--fg); }
h1 { font-size: 1.5em; margin: 0.2em 0; }
p { margin: 0.2em 0; color: var(--muted); }
table.metrics { border-collapse: collapse; margin: 0.6em 0; font-variant-numeric: tabular-nums; }
table.metrics th, table.metrics td { border-bottom: 1px solid var(--line); padding: 2px 8px; text-align: left; }
table.metrics th { cursor: pointer; user-select: none; }
table.metrics td.num { text-align: right; }
table.metrics td.best { font-weight: bold; }
table.metrics tr[data-layer] { cursor: pointer; }
table.metrics tr.current { outline: 2px solid var(--hl); }
#toolbar { display: flex; flex-wrap: wrap; gap: 4px; align-items: center; margin: 0.5em 0; }
#toolbar button, #controls button { font: inherit; padding: 2px 8px; border: 1px solid var(--line); border-radius: 3px;
  background: transparent; color: inherit; cursor: pointer; }
#toolbar button[aria-pressed="true"], #controls button[aria-pressed="true"] {
  background: var(--hl); color: #fff; border-color: var(--hl); }
#toolbar kbd, #controls kbd { font-size: 0.8em; opacity: 0.7; margin-right: 3px; }
#controls { display: flex; flex-wrap: wrap; gap: 14px; align-items: center; margin: 0.4em 0; }
#viewport { position: relative; width: min(100%, 768px); height: 512px; overflow: hidden; cursor: grab;
  background: repeating-conic-gradient(#808080 0% 25%, #a0a0a0 0% 50%) 50% / 16px 16px;
  border: 1px solid var(--line); touch-action: none; user-select: none; }
#viewport.dragging { cursor: grabbing; }
#stage { position: absolute; left: 0; top: 0; transform-origin: 0 0; }
#view { display: block; image-rendering: crisp-edges; image-rendering: pixelated; -webkit-user-drag: none; }
#status { font-variant-numeric: tabular-nums; color: var(--muted); min-height: 1.4em; }
#legend { display: flex; visibility: hidden; align-items: center; gap: 6px; color: var(--muted); }
#legend.on { visibility: visible; }
#legend .bar { width: 200px; height: 12px; border: 1px solid var(--line);
  background: linear-gradient(to right, #440154, #3b528b, #21918c, #5ec962, #fde725); }
figure { display: inline-block; margin: 0.5em 1em 0.5em 0; }
img.plot { max-width: 480px; }
details { margin: 1em 0; }
"""

_JS = r"""
(function () {
  "use strict";
  const D = JSON.parse(document.getElementById("report-data").textContent);
  const W = D.width, H = D.height, L = D.layers;
  const vp = document.getElementById("viewport"), stage = document.getElementById("stage");
  const img = document.getElementById("view"), status = document.getElementById("status");
  const bar = document.getElementById("layers"), legend = document.getElementById("legend");
  const legendText = document.getElementById("legend-text");
  const slider = document.getElementById("exposure"), evOut = document.getElementById("ev");
  const zoomOut = document.getElementById("zoom");
  let cur = 0, prev = 0, view = "image", ev = 0, s = 1, tx = 0, ty = 0, fitted = false;

  function keyName(i) {
    if (i < 10) return String((i + 1) % 10);
    if (i < 20) return "⇧" + String((i - 9) % 10);
    return "";
  }
  L.forEach(function (la, i) {
    const b = document.createElement("button");
    b.type = "button";
    b.dataset.layer = la.id;
    b.innerHTML = (keyName(i) ? "<kbd>" + keyName(i) + "</kbd>" : "");
    b.appendChild(document.createTextNode(la.label));
    b.title = la.label + (keyName(i) ? " (key " + keyName(i) + ")" : "");
    b.addEventListener("click", function () { show(i); });
    bar.appendChild(b);
  });

  function applyTransform() {
    stage.style.transform = "translate(" + tx + "px, " + ty + "px) scale(" + s + ")";
    stage.dataset.scale = String(s);
    zoomOut.textContent = (s >= 1 ? s.toFixed(s < 10 ? 2 : 1) : s.toPrecision(2)) + "×";
  }
  // The viewport takes the window's height below its top, at most 512 px, so that the whole image and
  // its caption are in view in the opened page (a 1000-px-high window included).
  function sizeViewport() {
    const top = vp.getBoundingClientRect().top + window.scrollY;
    const caption = document.getElementById("caption").offsetHeight || 20;
    const room = window.innerHeight - top - caption - 16;
    vp.style.height = Math.max(160, Math.min(512, Math.floor(room))) + "px";
  }
  function fit() {
    const vw = vp.clientWidth, vh = vp.clientHeight;
    let f = Math.min(vw / W, vh / H);
    if (f >= 1) f = Math.floor(f);
    s = f > 0 ? f : 1;
    tx = Math.round((vw - W * s) / 2);
    ty = Math.round((vh - H * s) / 2);
    fitted = true;
    applyTransform();
  }
  function applyExposure() {
    const f = Math.pow(2, ev / 2.2);
    img.style.filter = img.dataset.view === "image" && ev !== 0 ? "brightness(" + f.toFixed(4) + ")" : "none";
    evOut.textContent = (ev > 0 ? "+" : "") + ev.toFixed(2) + " EV";
  }
  function show(i, newView) {
    if (i < 0 || i >= L.length) return;
    if (i !== cur) { prev = cur; cur = i; }
    if (newView) view = newView;
    const la = L[cur];
    let shown = view, note = "";
    if (view === "error" && !la.error) { shown = "image"; note = " (no error map: this is the reference)"; }
    if (view === "density" && !la.density) { shown = "image"; note = " (no sample density: not an adaptive run)"; }
    img.src = shown === "error" ? la.error : shown === "density" ? la.density : la.image;
    img.alt = la.label + " " + shown;
    img.dataset.layer = la.id;
    img.dataset.view = shown;
    bar.querySelectorAll("button").forEach(function (b, j) {
      b.setAttribute("aria-pressed", j === cur ? "true" : "false");
    });
    document.querySelectorAll("#view-modes button").forEach(function (b) {
      b.setAttribute("aria-pressed", b.dataset.view === view ? "true" : "false");
    });
    document.querySelectorAll("table.metrics tr[data-layer]").forEach(function (tr) {
      tr.classList.toggle("current", tr.dataset.layer === la.id);
    });
    if (shown === "error") {
      legend.classList.add("on");
      legendText.textContent = "relative squared error (log), black = 0; mean " + la.error_mean.toPrecision(4);
    } else if (shown === "density") {
      legend.classList.add("on");
      legendText.textContent = "samples per pixel, 0 … " + la.density_max;
    } else {
      legend.classList.remove("on");
    }
    document.getElementById("legend-lo").textContent = shown === "density" ? "0" : D.error_range[0].toExponential(0);
    document.getElementById("legend-hi").textContent =
      shown === "density" ? String(la.density_max) : String(D.error_range[1]);
    document.getElementById("current").textContent = la.label + " — " + shown + note;
    applyExposure();
  }

  vp.addEventListener("wheel", function (e) {
    e.preventDefault();
    const r = vp.getBoundingClientRect();
    const mx = e.clientX - r.left, my = e.clientY - r.top;
    let dy = e.deltaY * (e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? 400 : 1);
    dy = Math.max(-300, Math.min(300, dy));
    const ns = Math.max(0.05, Math.min(512, s * Math.pow(2, -dy / 200)));
    tx = mx - (mx - tx) * ns / s;
    ty = my - (my - ty) * ns / s;
    s = ns;
    fitted = false;
    applyTransform();
  }, { passive: false });

  let drag = null;
  vp.addEventListener("pointerdown", function (e) {
    if (e.button !== 0) return;
    drag = { x: e.clientX, y: e.clientY, tx: tx, ty: ty };
    vp.classList.add("dragging");
    try { vp.setPointerCapture(e.pointerId); } catch (err) { /* synthetic pointers */ }
    e.preventDefault();
  });
  vp.addEventListener("pointermove", function (e) {
    const r = vp.getBoundingClientRect();
    if (drag) {
      tx = drag.tx + (e.clientX - drag.x);
      ty = drag.ty + (e.clientY - drag.y);
      fitted = false;
      applyTransform();
    }
    const px = Math.floor((e.clientX - r.left - tx) / s), py = Math.floor((e.clientY - r.top - ty) / s);
    status.textContent = (px >= 0 && py >= 0 && px < W && py < H) ? "pixel x " + px + ", y " + py : "";
  });
  function endDrag() { drag = null; vp.classList.remove("dragging"); }
  vp.addEventListener("pointerup", endDrag);
  vp.addEventListener("pointercancel", endDrag);
  vp.addEventListener("dblclick", fit);

  slider.addEventListener("input", function () { ev = parseFloat(slider.value) || 0; applyExposure(); });
  function setEv(v) {
    ev = Math.max(parseFloat(slider.min), Math.min(parseFloat(slider.max), v));
    slider.value = String(ev);
    applyExposure();
  }
  document.getElementById("ev-reset").addEventListener("click", function () { setEv(0); });
  document.getElementById("fit").addEventListener("click", fit);
  document.querySelectorAll("#view-modes button").forEach(function (b) {
    b.addEventListener("click", function () { show(cur, b.dataset.view); });
  });

  document.addEventListener("keydown", function (e) {
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const m = /^Digit(\d)$/.exec(e.code || "");
    if (m) {
      let i = (parseInt(m[1], 10) + 9) % 10;
      if (e.shiftKey) i += 10;
      if (i < L.length) { show(i); e.preventDefault(); }
      return;
    }
    switch (e.key) {
      case "ArrowRight": show((cur + 1) % L.length); break;
      case "ArrowLeft": show((cur + L.length - 1) % L.length); break;
      case " ": show(prev); break;
      case "e": case "E": show(cur, view === "error" ? "image" : "error"); break;
      case "d": case "D": show(cur, view === "density" ? "image" : "density"); break;
      case "i": case "I": show(cur, "image"); break;
      case "f": case "F": fit(); break;
      case "+": case "=": setEv(ev + 0.5); break;
      case "-": case "_": setEv(ev - 0.5); break;
      default: return;
    }
    e.preventDefault();
  });

  document.querySelectorAll("table.metrics").forEach(function (t) {
    t.querySelectorAll("tr[data-layer]").forEach(function (tr) {
      tr.addEventListener("click", function () {
        const i = L.findIndex(function (la) { return la.id === tr.dataset.layer; });
        if (i >= 0) { show(i); vp.scrollIntoView({ block: "nearest" }); }
      });
    });
    t.querySelectorAll("th").forEach(function (th) {
      th.addEventListener("click", function () {
        const col = parseInt(th.dataset.col, 10), body = t.tBodies[0];
        const asc = th.dataset.dir !== "asc";
        t.querySelectorAll("th").forEach(function (o) { delete o.dataset.dir; });
        th.dataset.dir = asc ? "asc" : "desc";
        const rows = Array.prototype.slice.call(body.rows);
        rows.sort(function (a, b) {
          const ca = a.cells[col], cb = b.cells[col];
          const va = ca.dataset.v !== undefined ? parseFloat(ca.dataset.v) : ca.textContent;
          const vb = cb.dataset.v !== undefined ? parseFloat(cb.dataset.v) : cb.textContent;
          const c = (typeof va === "number" && typeof vb === "number") ? va - vb : String(va).localeCompare(String(vb));
          return asc ? c : -c;
        });
        rows.forEach(function (r) { body.appendChild(r); });
      });
    });
  });

  window.addEventListener("resize", function () { sizeViewport(); if (fitted) fit(); });
  sizeViewport();
  fit();
  show(0);
  document.body.dataset.ready = "1";
})();
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta http-equiv="Content-Security-Policy"
  content="default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'">
<title>{title}</title>
<style>{css}</style>
</head>
<body>
<h1>{title}</h1>
{info}
<h2>Viewer</h2>
<p class="keys">Keys: 1…9, 0 (⇧ + digit for layers 11…20), ← → pick a layer at the same zoom and pan;
Space flips back to the previous one; wheel zooms about the cursor, drag pans, double-click or f fits;
e error map, d sample density, i image; + / − exposure. Exposure is a CSS brightness of 2^(EV/2.2) on the
8-bit sRGB previews (highlights clipped in the preview stay clipped).</p>
<div id="toolbar"><span id="layers" style="display:contents"></span></div>
<div id="controls">
  <span id="view-modes"><button type="button" data-view="image">image <kbd>i</kbd></button>
  <button type="button" data-view="error">error map <kbd>e</kbd></button>
  <button type="button" data-view="density">density <kbd>d</kbd></button></span>
  <label>exposure <input id="exposure" type="range" min="-8" max="8" step="0.25" value="0"></label>
  <output id="ev">0.00 EV</output> <button type="button" id="ev-reset">0 EV</button>
  <button type="button" id="fit">fit <kbd>f</kbd></button> zoom <output id="zoom">1×</output>
  <span id="legend"><span id="legend-lo">{lo}</span><span class="bar"></span><span id="legend-hi">{hi}</span>
  <span id="legend-text"></span></span>
</div>
<div id="viewport"><div id="stage"><img id="view" alt="" draggable="false"></div></div>
<div id="caption"><strong id="current"></strong> <span id="status"></span></div>
<h2>Metrics</h2>
{table}
{figures}
<details><summary>every point of the run ({n_points})</summary>
{all_table}
</details>
<script type="application/json" id="report-data">{data}</script>
<script>{js}</script>
</body>
</html>
"""

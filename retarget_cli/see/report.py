"""A self-contained HTML report of a run (``retarget report``).

One HTML file with every image embedded as a base64 PNG, no scripts, no
external stylesheet or font: it can be mailed, archived next to a shot or
opened offline. Each section appears only when the run has its data:

- run summary: take, inputs, settings and stage timings (from the stage manifests);
- tracking confidence over time (``landmarks.npz``);
- the rest pose: the neutral frame ``keys.json`` and the stage manifests record, why it was chosen
  (``neutral_frame: auto``), the source frame and the character there;
- key shapes: the source key frames next to renders of the target keys
  (``keys.json``, the source video, ``targets.yaml``);
- E against k (eq. 5 of Chuang & Bregler 2002) from ``select``'s evaluation
  curve CSV, when the run has one;
- weight curves per region (``weights.npz``);
- residual (the eq. 4 fit's error) and jitter per frame, with the worst frames
  listed and thumbnailed;
- cardinality and objective per frame, when a rig solve stored them;
- on a synthetic take (``truth.npz`` beside the video, or ``--truth``): mesh
  error and mesh jitter against the true animation, as a ratio to the truth's,
  and the same for the tracked and reconstructed landmarks (issue #16).

Plots use matplotlib (optional: ``pip install 'retarget[report]'``) through
its Agg canvas, without pyplot's global state. Output is deterministic: no
timestamps, PNG metadata without software or dates.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import logging
import os
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError, RetargetError
from ..io.atomic import check_not_input, load_npz, write_text
from ..io.landmarks import load_landmarks
from ..io.obj import read_obj
from ..io.stagefiles import read_targets
from ..methods.decomposition import mean_acceleration
from ..methods.gaps import gap_summary
from ..methods.render import Camera, MeshRenderer
from ..run.pipeline import STAGES
from ..run.runfiles import RunFiles
from ..stages.auto_pose import COVERAGE_JSON
from .preview import REGION_COLORS, RunData, _blank, draw_landmarks, put_text
from .preview import FrameSource as RowFrames
from .truth import load_truth_animation, mesh_against_truth, points_against_truth

log = logging.getLogger(__name__)

#: Frames on either side of a listed worst frame that are not listed again.
WORST_SUPPRESS = 3
#: Keys shown per region in the contact sheet (more are summarised).
MAX_SHEET_KEYS = 24
THUMB = 120

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1100px;
padding:0 20px 40px;color:#222;background:#fafafa;line-height:1.4}
h1{font-size:1.6em;margin:24px 0 4px}h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:4px;margin-top:32px}
nav a{margin-right:12px}section{margin-bottom:24px}
table{border-collapse:collapse;margin:8px 0;font-size:.9em}td,th{border:1px solid #ddd;padding:3px 8px;text-align:left;
vertical-align:top}th{background:#eee}td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:12px 0}figure img{max-width:100%;border:1px solid #ddd;background:#fff}
figcaption{font-size:.85em;color:#555}details{margin:8px 0}summary{cursor:pointer;font-weight:600}code{font-size:.9em}.muted{color:#777}.thumb img{height:96px;margin-right:2px}
"""


def _matplotlib():
    """The matplotlib pieces used here, imported lazily (Agg canvas, no pyplot)."""
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise RetargetError("retarget report needs matplotlib: pip install 'retarget[report]' "
                            "(make demo installs it)") from exc
    return matplotlib, Figure, FigureCanvasAgg


def _figure(width=9.0, height=3.0, nrows=1, ncols=1, **kw):
    _, Figure, FigureCanvasAgg = _matplotlib()
    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _frame_axis(a, data: RunData, T: int) -> None:
    """Label the x axis of *a*, whose positions are rows 0 … T−1 of the take, with the rows' source frame
    numbers (a take tracked from ``start: 100, step: 2`` reads 100, 110, … under rows 0, 5, …)."""
    numbers = data.numbers(T)
    if T == 0 or np.array_equal(numbers, np.arange(T)):
        a.set_xlabel("frame")
        return
    def label(x, _pos):
        r = int(round(x))
        return str(int(numbers[r])) if 0 <= r < T and abs(x - r) < 1e-6 else ""

    ticker = _matplotlib()[0].ticker
    a.xaxis.set_major_locator(ticker.MaxNLocator(integer=True))  # ticks on rows, each labelled by its frame
    a.xaxis.set_major_formatter(ticker.FuncFormatter(label))
    a.set_xlabel("frame (source frame number)")


def _png_fig(fig) -> bytes:
    """PNG bytes of a matplotlib figure, with no metadata that changes between runs."""
    matplotlib, _, _ = _matplotlib()
    buf = io.BytesIO()
    with matplotlib.rc_context({"svg.hashsalt": "retarget"}):
        fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _png_img(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:  # pragma: no cover
        raise RetargetError("OpenCV could not encode a PNG")
    return buf.tobytes()


def _img_tag(png: bytes, alt: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img{c} alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _figure_html(png: bytes, caption: str) -> str:
    return f"<figure>{_img_tag(png, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>"


def _table(header, rows, num_cols=()) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = []
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            raw = isinstance(c, _Raw)
            text = c.html if raw else html.escape(str(c))
            cls = ' class="num"' if i in num_cols else ""
            cells.append(f"<td{cls}>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{h}</tr></thead><tbody>{''.join(body)}</tbody></table>"


class _Raw:
    """Trusted HTML for a table cell."""

    def __init__(self, html_text: str):
        self.html = html_text


def _ranges(ids) -> str:
    """``[17, 18, 19, 21]`` -> ``"17-19, 21"``."""
    ids = sorted(int(i) for i in ids)
    out, start = [], None
    for i, v in enumerate(ids):
        if start is None:
            start = v
        if i + 1 == len(ids) or ids[i + 1] != v + 1:
            out.append(f"{start}-{v}" if v > start else f"{v}")
            start = None
    return ", ".join(out)


def _show(path) -> str:
    """A path as shown in the report: relative to the working directory when below it."""
    p = os.path.normpath(os.path.abspath(path))
    rel = os.path.relpath(p, os.getcwd())
    return rel if not rel.startswith("..") else p


def _fmt_setting(v) -> str:
    if isinstance(v, list) and v and all(isinstance(i, int) for i in v):
        return _ranges(v)
    if isinstance(v, dict):
        return "; ".join(f"{k}: {_fmt_setting(x)}" for k, x in v.items())
    if v is None:
        return "none"
    return str(v)


# --------------------------------------------------------------------------- per-frame quantities


def jitter_per_frame(W: np.ndarray) -> np.ndarray:
    """Per-frame jitter: mean over keys of the squared second difference of the weights.

    .. math:: j_t = \\frac{1}{K} \\sum_k (w_{t+1,k} - 2 w_{t,k} + w_{t-1,k})^2

    (the per-frame term of the jitter score, the mean squared second
    difference of the weight curves).

    Parameters
    ----------
    W : ndarray, shape (T, K)

    Returns
    -------
    ndarray, shape (T,)
        Zero at the first and last frame.
    """
    W = np.asarray(W, dtype=np.float64)
    out = np.zeros(W.shape[0])
    if W.shape[0] >= 3:
        out[1:-1] = np.mean((W[2:] - 2 * W[1:-1] + W[:-2]) ** 2, axis=1)
    return out


def worst_frames(score: np.ndarray, n: int, suppress: int = WORST_SUPPRESS) -> list[int]:
    """The *n* frames with the highest *score*, no two within *suppress* frames of each other.

    Ties go to the earlier frame; non-finite and non-positive scores are never listed.
    """
    score = np.asarray(score, dtype=np.float64)
    order = np.lexsort((np.arange(len(score)), -np.nan_to_num(score, nan=-np.inf)))
    taken: list[int] = []
    for t in order:
        if len(taken) >= n or not np.isfinite(score[t]) or score[t] <= 0:
            break
        if all(abs(int(t) - s) > suppress for s in taken):
            taken.append(int(t))
    return taken


def _residual_rms(data: RunData, keys: dict) -> dict:
    """Region name to per-frame residual as RMS pixels per landmark (or the stored norm)."""
    out = {}
    for name in data.regions:
        res = data.extras.get(name, {}).get("residual")
        if res is None or np.ndim(res) != 1:
            continue
        n_pts = len(keys.get(name, {}).get("points", [])) if keys else 0
        out[name] = np.asarray(res, dtype=np.float64) / (np.sqrt(n_pts) if n_pts else 1.0)
    return out


# --------------------------------------------------------------------------- images from the take


def grab_frames(video: Path | None, indices, numbers=None) -> dict:
    """Decode the given rows of the take from *video* (a video or an image sequence) in one pass: row to image
    (empty dict without a video).

    *numbers* (T,): each row's source frame number (``landmarks.npz`` ``frames``; a take tracked from
    ``start: 100, step: 2`` reads source frames 100, 102, …); default the row itself.
    """
    wanted = sorted(set(int(i) for i in indices))
    if video is None or not wanted:
        return {}
    out = {}
    src = RowFrames(video, (1, 1), numbers)
    try:
        for t in wanted:
            img = src.get(t)
            if img is not None:
                out[t] = img
    finally:
        src.close()
    return out


def source_thumb(data: RunData, frames: dict, t: int, size: int = THUMB, highlight=None, color=(0, 200, 255)):
    """A square crop around frame *t*'s landmarks with them drawn (blank background without video)."""
    import cv2

    sw, sh = data.frame_size
    img = frames.get(t)
    if img is None:
        img = _blank((sw, sh), (80, 80, 80))
    if data.lm is None or t >= data.lm.n_frames:
        return cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    P = data.lm.points[t].astype(np.float64)
    ok = np.isfinite(P).all(1)
    lo, hi = P[ok].min(0), P[ok].max(0)
    c, half = (lo + hi) / 2, max(hi - lo) * 0.62 + 4
    x0, y0 = int(round(c[0] - half)), int(round(c[1] - half))
    side = int(round(2 * half))
    pad = cv2.copyMakeBorder(img, side, side, side, side, cv2.BORDER_CONSTANT, value=(80, 80, 80))
    crop = pad[y0 + side:y0 + 2 * side, x0 + side:x0 + 2 * side].copy()
    s = size / side
    crop = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA)
    Q = P - [x0, y0]
    if highlight is None:
        draw_landmarks(crop, Q, data.lm.confidence[t], scale=s, radius=1)
    else:
        mask = np.zeros(len(P), bool)
        mask[list(highlight)] = True
        for q, m in zip(Q * s, mask):
            if np.all(np.isfinite(q)):
                cv2.circle(crop, (int(round(q[0] * 16)), int(round(q[1] * 16))), (2 if m else 1) * 16,
                           color if m else (170, 170, 170), -1, cv2.LINE_AA, shift=4)
    return crop


def _label(img, text, color=(255, 255, 255)):
    import cv2

    cv2.rectangle(img, (0, 0), (img.shape[1], 15), (0, 0, 0), -1)
    put_text(img, text, (3, 11), 0.36, color)
    return img


# --------------------------------------------------------------------------- sections


def _section(sid: str, title: str, body: str) -> str:
    return f'<section id="{sid}"><h2>{html.escape(title)}</h2>{body}</section>'


def _file_params(stage: str) -> set:
    """Names of a stage's input and output parameters (shown as files, not settings)."""

    if stage not in STAGES:
        return set()
    return {p.name for p in STAGES[stage].params if p.kind in ("input", "output")} | {"base_dir"}


def _landmark_rows(data: RunData) -> list:
    """Summary rows about the landmarks file: point count, frame size, tracker, landmark filter."""
    w, h = data.frame_size
    rows = [("landmarks", f"{data.lm.n_points} points, {w}x{h} pixels")]
    if data.lm.meta.get("tracker"):
        rows.append(("tracker", str(data.lm.meta.get("tracker"))))
    if data.lm.found is not None:
        rows.append(("gaps", gap_summary(_gap_list(data.lm))))
    filt = data.lm.meta.get("filter")
    if isinstance(filt, dict) and filt.get("method"):
        params = ", ".join(f"{k} {v}" for k, v in filt.items() if k != "method")
        rows.append(("landmark filter", f"{filt['method']} ({params})" if params else str(filt["method"])))
    return rows


def _solver_rows(meta: dict) -> list:
    """Summary rows from the weights' meta: solver, and mesh-space jitter per region."""
    rows = []
    solver = meta.get("solver")
    if solver:
        rows.append(("solver", str(solver)))
    for name, d in sorted((meta.get("diagnostics") or {}).items()):
        if isinstance(d, dict) and "shape_jitter_px" in d:
            ratio = (f" ({d['shape_jitter_px'] / d['input_jitter_px']:.2f}× the input landmarks')"
                     if d.get("input_jitter_px") else "")
            rows.append((f"mesh-space jitter {name}", f"{d['shape_jitter_px']:.3g} px/frame² mean landmark "
                         f"acceleration{ratio}"))
    return rows


def _summary_rows(data: RunData, run: RunFiles, keys: dict) -> list:
    """The (name, value) rows of the run-summary table."""
    rows = [("run", _show(run.root))]
    if run.config:
        rows.append(("config", _show(run.config)))
    if run.video:
        rows.append(("video", _show(run.video)))
    if data.n_frames:
        rows.append(("frames", f"{data.n_frames} at {data.fps:g} fps ({data.n_frames / data.fps:.2f} s)"))
    if data.lm is not None:
        rows += _landmark_rows(data)
    for name, (W, _) in data.regions.items():
        err = keys.get(name, {}).get("error")
        extra = f", E = {err:.4g} px² (eq. 5)" if isinstance(err, (int, float)) else ""
        rows.append((f"region {name}", f"{W.shape[1]} keys{extra}"))
    if data.regions and data.other.get("meta"):
        rows += _solver_rows(data.other["meta"])
    if data.frame_files:
        rows.append(("target frames", f"{len(data.frame_files)} OBJ in {_show(run.frames)}"))
    elif data.character is not None:
        rows.append(("target frames", f"{data.n_character_frames} frames: the rig {_show(data.character[3])} posed "
                                      f"at {_show(data.character[2])} (no OBJ frames)"))
    return rows


def _inputs_html(man: dict) -> str:
    """The collapsible list of the run's input files (not produced by a stage), first 40 shown."""
    produced = {path for m in man.values() for path in (m.get("outputs") or {})}
    inp, seen = [], set()
    for stage, m in man.items():
        for path, rec in sorted((m.get("inputs") or {}).items()):
            if isinstance(rec, dict) and path not in produced and path not in seen:
                seen.add(path)
                inp.append((stage, path, rec.get("size", ""), str(rec.get("sha256", ""))[:12]))
    if not inp:
        return ""
    shown = inp[:40]
    more = (f'<p class="muted">and {len(inp) - len(shown)} more input files.</p>'
            if len(inp) > len(shown) else "")
    return (f"<details><summary>Inputs: {len(inp)} files (sizes and sha256)</summary>"
            + _table(("first used by", "file (relative to the config)", "bytes", "sha256"), shown,
                     num_cols=(2,)) + more + "</details>")


def _stages_html(man: dict) -> str:
    """The table of stages with their seconds, version and settings (file parameters left out)."""
    st = []
    for stage, m in man.items():
        settings = {k: v for k, v in (m.get("settings") or {}).items() if k not in _file_params(stage)}
        text = "; ".join(f"{k} = {_fmt_setting(v)}" for k, v in sorted(settings.items()))
        sec = m.get("seconds")
        st.append((stage, f"{sec:.2f}" if isinstance(sec, (int, float)) else "n/a", m.get("version", ""), text))
    return "<h3>Stages</h3>" + _table(("stage", "seconds", "version", "settings"), st, num_cols=(1,))


def _timings_html(timed: list) -> str:
    """Bar chart of ``[(stage, seconds)]``."""
    fig, ax = _figure(6, 0.45 + 0.22 * len(timed))
    ax = ax[0, 0]
    names = [s for s, _ in timed][::-1]
    secs = [v for _, v in timed][::-1]
    ax.barh(names, secs, color="#4a7fb5")
    for i, v in enumerate(secs):
        ax.text(v, i, f" {v:.2f} s", va="center", fontsize=8)
    ax.set_xlabel("seconds (wall clock, last run of each stage)")
    ax.set_xlim(0, max(secs) * 1.18 + 1e-3)
    return _figure_html(_png_fig(fig), "Stage timings from the manifests.")


def _summary(data: RunData, run: RunFiles, keys: dict) -> tuple[str, bool]:
    parts = [_table(("", ""), _summary_rows(data, run, keys))]
    man = run.manifests
    if man:
        parts.append(_inputs_html(man))
        parts.append(_stages_html(man))
    else:
        parts.append('<p class="muted">No stage manifests (.retarget/*.json): the stages were run one by one, '
                     "so inputs, settings and timings are unknown.</p>")
    timed = [(s, m["seconds"]) for s, m in man.items() if isinstance(m.get("seconds"), (int, float))]
    if timed:
        parts.append(_timings_html(timed))
    return _section("summary", "Run summary", "".join(parts)), bool(timed)


def _tracking(data: RunData) -> str | None:
    lm = data.lm
    if lm is None:
        return None
    conf = lm.confidence.astype(np.float64)
    T = lm.n_frames
    t = np.arange(T)
    lost = conf <= 1e-3
    fig, ax = _figure(9, 4.2, 2, 1, sharex=True, gridspec_kw={"height_ratios": [1, 1.3]})
    a = ax[0, 0]
    a.plot(t, conf.mean(1), color="#2a7", lw=1.2, label="mean")
    a.plot(t, conf.min(1), color="#d62", lw=0.8, label="lowest landmark")
    frac = lost.mean(1)
    if frac.any():
        a.fill_between(t, 0, frac, color="#d33", alpha=0.3, step="mid", label="fraction lost")
    gaps = _gap_list(lm)
    for i, (g0, g1) in enumerate(_gap_spans(lm)):
        a.axvspan(g0 - 0.5, g1 - 0.5, color="#888", alpha=0.25, lw=0, label="gap (no face)" if i == 0 else None)
    a.set_ylim(-0.02, 1.02)
    a.set_ylabel("confidence")
    a.legend(loc="lower left", fontsize=8, ncol=4)
    b = ax[1, 0]
    im = b.imshow(conf.T, aspect="auto", cmap="RdYlGn", vmin=0, vmax=1, interpolation="nearest",
                  extent=(-0.5, T - 0.5, lm.n_points - 0.5, -0.5))
    b.set_ylabel("landmark")
    _frame_axis(b, data, T)
    fig.colorbar(im, ax=b, fraction=0.03, pad=0.01)
    n_lost = int(lost.any(1).sum())
    worst = int(np.argmin(conf.mean(1)))
    body = (f"<p>Mean confidence {conf.mean():.3f}; {n_lost} of {T} frames have a lost landmark "
            f"(confidence 0); lowest mean confidence {conf.mean(1)[worst]:.3f} at frame {worst}.</p>")
    body += _gaps_html(gaps, lm)
    body += _figure_html(_png_fig(fig), "Tracking confidence per frame (top; grey: gaps) and per landmark "
                                        "(bottom; red = lost).")
    return _section("tracking", "Tracking confidence", body)


def _gap_list(lm) -> list:
    """The gaps ``track`` recorded in the landmarks' meta (``[]`` when none or not recorded)."""
    gaps = lm.meta.get("gaps")
    return [g for g in gaps if isinstance(g, dict)] if isinstance(gaps, list) else []


def _gap_spans(lm) -> list:
    """Row ranges ``(start, stop)`` of the frames without a face (landmarks.npz's ``found``)."""
    if lm.found is None:
        return []
    f = np.asarray(lm.found, bool)
    out, t = [], 0
    while t < len(f):
        if f[t]:
            t += 1
            continue
        end = t + int(np.argmax(f[t:])) if f[t:].any() else len(f)
        out.append((t, end))
        t = end
    return out


def _gaps_html(gaps: list, lm) -> str:
    """The take's gaps: one line, and a table of where each is, how long, and why."""
    if lm.found is None:
        return ""
    if not gaps:
        return "<p>No gaps: the face was found in every frame, and no scene cut.</p>"
    rows = [(str(g.get("start")), str(g.get("frames")), f"{g.get('seconds', 0):.2f}" if "seconds" in g else "",
             str(g.get("reason")), "yes" if g.get("cut") else "") for g in gaps]
    return (f"<p>{html.escape(gap_summary(gaps))}, {int(np.sum(~np.asarray(lm.found, bool)))} of {lm.n_frames} "
            f"frames without a face; each segment between them is tracked and smoothed on its own, and the curves "
            f"there follow <code>apply.gaps</code>.</p>"
            + _table(["start frame", "frames", "seconds", "why", "scene cut"], rows, num_cols=(0, 1, 2)))


def _sheet_regions(data: RunData, keys: dict) -> dict:
    """Regions with key frames: from ``keys.json``, else the weights file's key frames; each with ``frames``
    (source frame numbers) and ``rows`` (rows of the take, None for a frame that is not one of it)."""
    regions = {n: dict(r) for n, r in keys.items() if r.get("frames")}
    if not regions and data.regions:
        regions = {n: {"frames": [int(f) for f in fr], "points": None} for n, (_, fr) in data.regions.items()}
    for reg in regions.values():  # the frames decide (a keys.json edited by hand may hold stale rows)
        reg["rows"] = [data.row_of(int(f)) for f in reg["frames"]]
    return regions


def _sheet_renderer(run: RunFiles, camera, shading):
    """``(targets, renderer)`` for the target key shapes; either is None when unreadable or absent."""
    targets = None
    if run.targets:

        try:
            targets = read_targets(run.targets)
        except InputError as exc:
            log.warning("%s", exc)
    if targets is None:
        return None, None

    ref_path = targets.neutral or next(iter(next(iter(targets.regions.values()))["keys"].values()))
    if not Path(ref_path).is_file():
        return targets, None
    ref = read_obj(ref_path)
    return targets, MeshRenderer(ref.faces(), ref.vertices, camera=camera, size=(THUMB, THUMB), shading=shading)


def _target_thumb(renderer, targets, name: str, f: int, col) -> np.ndarray:
    """Render of region *name*'s target key shape at frame *f*, or a grey "no target" tile."""

    if name in targets.regions and f in targets.regions[name]["keys"]:
        p = targets.regions[name]["keys"][f]
        if Path(p).is_file():
            m = read_obj(p)
            if m.n_vertices == renderer.n_vertices:
                return _label(renderer.render(m.vertices), f"target {f}", col)
    return _label(_blank((THUMB, THUMB), (60, 60, 60)), "no target")


def _sheet_rows(data: RunData, frames: dict, regions: dict, targets, renderer) -> tuple[list, list]:
    """Contact-sheet image rows (source thumbnails, then target renders when there is a renderer) and notes."""
    rows = []
    notes = []
    for r, (name, reg) in enumerate(regions.items()):
        col = REGION_COLORS[r % len(REGION_COLORS)]
        fr = [int(f) for f in reg["frames"]]
        rows_ = reg["rows"]
        if len(fr) > MAX_SHEET_KEYS:
            notes.append(f"{name}: first {MAX_SHEET_KEYS} of {len(fr)} keys shown")
            fr, rows_ = fr[:MAX_SHEET_KEYS], rows_[:MAX_SHEET_KEYS]
        top = [_label(source_thumb(data, frames, r, highlight=reg.get("points"), color=col) if r is not None
                      else _blank((THUMB, THUMB), (60, 60, 60)), f"{name} {f}", col) for f, r in zip(fr, rows_)]
        rows.append(np.hstack(top))
        if renderer is not None:
            rows.append(np.hstack([_target_thumb(renderer, targets, name, f, col) for f in fr]))
    return rows, notes


def _keys_sheet(data: RunData, run: RunFiles, keys: dict, frames: dict, camera, shading) -> str | None:
    import cv2

    regions = _sheet_regions(data, keys)
    if not regions:
        return None
    targets, renderer = _sheet_renderer(run, camera, shading)
    rows, notes = _sheet_rows(data, frames, regions, targets, renderer)
    width = max(r.shape[1] for r in rows)
    sheet = np.vstack([cv2.copyMakeBorder(r, 0, 4, 0, width - r.shape[1], cv2.BORDER_CONSTANT, value=(255, 255, 255))
                       for r in rows])
    what = "source key frames (region landmarks highlighted)"
    if renderer is not None:
        what += " above renders of the target key shapes from " + _show(run.targets)
    body = ""
    if notes:
        body += f'<p class="muted">{html.escape("; ".join(notes))}.</p>'
    table = [(n, len(reg["frames"]), ", ".join(str(f) for f in reg["frames"]),
              f"{reg['error']:.4g}" if isinstance(reg.get("error"), (int, float)) else "")
             for n, reg in regions.items()]
    body += _table(("region", "k", "key frames", "E (eq. 5, px²)"), table, num_cols=(1, 3))
    body += _figure_html(_png_img(sheet), f"Key-shape contact sheet: {what}.")
    return _section("keys", "Key shapes", body)


def read_curve(path: Path) -> dict:
    """Read an E-against-k CSV into ``{panel: {series: (k, E)}}``.

    Accepted layouts: long (a ``k`` column, one value column named ``E``,
    ``error`` or the only numeric one, and text columns such as ``region`` and
    ``method`` naming the series), or wide (``k`` then one numeric column per
    series). A ``region`` column gives one panel per region.
    """
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    if len(rows) < 2:
        raise InputError(f"{path}: expected a header and at least one row")
    header = [h.strip() for h in rows[0]]
    low = [h.lower() for h in header]
    if "k" not in low:
        raise InputError(f"{path}: no 'k' column (columns: {', '.join(header)})")
    ki = low.index("k")
    body = [r + [""] * (len(header) - len(r)) for r in rows[1:]]

    def numeric(j):
        try:
            [float(r[j]) for r in body if r[j] != ""]
            return any(r[j] != "" for r in body)
        except ValueError:
            return False

    num = [j for j in range(len(header)) if j != ki and numeric(j)]
    # A ``frames`` column (the key frames of each row, as select writes) names no series.
    text = [j for j in range(len(header)) if j != ki and j not in num and low[j] != "frames"]
    val = next((j for j in num if low[j] in ("e", "error", "reconstruction_error")), None)
    panels: dict = {}
    ri = low.index("region") if "region" in low else None
    if val is not None or (text and len(num) == 1):
        val = num[0] if val is None else val
        for r in body:
            panel = r[ri] if ri is not None else ""
            series = " ".join(r[j] for j in text if j != ri) or header[val]
            if r[val] == "" or r[ki] == "":
                continue
            panels.setdefault(panel, {}).setdefault(series, []).append((float(r[ki]), float(r[val])))
    else:
        for j in num:
            for r in body:
                if r[j] != "" and r[ki] != "":
                    panel = r[ri] if ri is not None else ""
                    panels.setdefault(panel, {}).setdefault(header[j], []).append((float(r[ki]), float(r[j])))
    out = {}
    for p, ser in panels.items():
        out[p] = {}
        for s, pts in ser.items():
            pts = sorted(pts)
            out[p][s] = (np.array([a for a, _ in pts]), np.array([b for _, b in pts]))
    if not out:
        raise InputError(f"{path}: no (k, E) values found")
    return out


def _curve(run: RunFiles, keys: dict) -> str | None:
    if run.curve is None:
        return None
    try:
        panels = read_curve(run.curve)
    except (InputError, OSError, UnicodeDecodeError) as exc:
        log.warning("E-vs-k curve skipped: %s", exc)
        return None
    n = len(panels)
    fig, ax = _figure(min(4.5 * n, 13.5), 3.2, 1, n)
    for i, (panel, series) in enumerate(sorted(panels.items())):
        a = ax[0, i]
        for s, (k, e) in sorted(series.items()):
            a.plot(k, e, marker="o", ms=3, lw=1.2, label=s)
        chosen = keys.get(panel, {}).get("frames") if panel else None
        if chosen:
            a.axvline(len(chosen), color="#888", ls=":", lw=1)
        a.set_xlabel("k (key shapes)")
        a.set_ylabel("E (eq. 5, px²)")
        a.set_yscale("log" if all((e > 0).all() for _, e in series.values()) else "linear")
        a.set_title(panel or "all regions", fontsize=10)
        a.legend(fontsize=7)
    body = _figure_html(_png_fig(fig), f"Reconstruction error E against the number of keys k, from {_show(run.curve)} "
                                       "(dotted: the k of this run).")
    return _section("curve", "Reconstruction error against k", body)


def _weights(data: RunData) -> str | None:
    if not data.regions:
        return None
    n = len(data.regions)
    fig, ax = _figure(9, 0.6 + 2.4 * n, n, 1, sharex=True)
    cmap = _matplotlib()[0].colormaps["tab20"]
    for i, (name, (W, fr)) in enumerate(data.regions.items()):
        a = ax[i, 0]
        t = np.arange(W.shape[0])
        for k in range(W.shape[1]):
            a.plot(t, W[:, k], lw=0.9, color=cmap(k % 20), label=str(int(fr[k])))
        for k, f in enumerate(fr):  # a key is named by its source frame; drawn at its row
            r = data.row_of(int(f))
            if r is not None:
                a.plot([r], [W[:, k].max() if W.shape[0] else 0], marker="v", ms=4, color=cmap(k % 20), ls="none")
        a.set_ylabel(f"{name}\nweight")
        a.legend(title="key frame", fontsize=6, title_fontsize=7, ncol=1 + (W.shape[1] > 8) + (W.shape[1] > 24),
                 loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    _frame_axis(ax[-1, 0], data, next(iter(data.regions.values()))[0].shape[0])
    body = _figure_html(_png_fig(fig), "Weights per region and key (triangles: each key's own frame, at its "
                                       "curve's maximum).")
    return _section("weights", "Weight curves", body)


def _residuals(data: RunData, keys: dict, frames: dict, worst: int, mesh_renderer) -> str | None:
    if not data.regions:
        return None
    res = _residual_rms(data, keys)
    jit = {}
    for name, (W, _) in data.regions.items():
        stored = data.extras.get(name, {}).get("jitter")
        jit[name] = (np.asarray(stored, dtype=np.float64) if stored is not None and np.shape(stored) == (W.shape[0],)
                     else jitter_per_frame(W))
    T = next(iter(data.regions.values()))[0].shape[0]
    per_pt = all(len(keys.get(n, {}).get("points", [])) for n in res) and bool(keys)
    unit = "RMS px per landmark" if per_pt else "norm, px"
    n_plots = 1 + bool(res)
    fig, ax = _figure(9, 1.0 + 2.2 * n_plots, n_plots, 1, sharex=True)
    t = np.arange(T)
    res_total = np.sum([r[:T] for r in res.values()], axis=0) if res else None
    jit_total = np.sum([j[:T] for j in jit.values()], axis=0)
    worst_res = worst_frames(res_total, worst) if res_total is not None else []
    worst_jit = worst_frames(jit_total, worst)
    i = 0
    if res:
        a = ax[0, 0]
        for r, (name, v) in enumerate(res.items()):
            a.plot(t, v[:T], lw=1, label=name, color=np.array(REGION_COLORS[r % len(REGION_COLORS)][::-1]) / 255)
        for f in worst_res:
            a.axvline(f, color="#c33", lw=0.6, alpha=0.6)
        a.set_ylabel(f"residual\n({unit})")
        a.legend(fontsize=8, loc="upper left")
        lost = [data.extras.get(n, {}).get("lost") for n in data.regions]
        for lf in lost:
            if lf is not None and np.shape(lf) == (T,) and np.any(lf):
                a.fill_between(t, 0, 1, where=np.asarray(lf, bool), transform=a.get_xaxis_transform(),
                               color="#d33", alpha=0.15, step="mid")
        i = 1
    a = ax[i, 0]
    for r, (name, v) in enumerate(jit.items()):
        a.plot(t, v[:T], lw=1, label=name, color=np.array(REGION_COLORS[r % len(REGION_COLORS)][::-1]) / 255)
    for f in worst_jit:
        a.axvline(f, color="#36c", lw=0.6, alpha=0.6)
    a.set_ylabel("jitter\n(mean sq. 2nd diff.)")
    a.set_yscale("symlog", linthresh=max(float(np.percentile(jit_total, 50)), 1e-9))
    a.set_ylim(bottom=0)
    a.legend(fontsize=8)
    _frame_axis(ax[-1, 0], data, T)
    caption = ("Per-frame residual of the weight fit (eq. 4) and jitter of the weights; vertical lines mark the "
               "frames listed below (red: residual, blue: jitter).")
    body = _figure_html(_png_fig(fig), caption)
    listed = [(f, "residual") for f in worst_res] + [(f, "jitter") for f in worst_jit if f not in worst_res]
    if listed:
        rows = []
        for f, why in listed:
            number, seconds = data.source_time(f)
            cells = [number, f"{seconds:.2f}", why]
            cells += [f"{res[n][f]:.3g}" for n in res]
            cells += [f"{jit_total[f]:.3g}"]
            if data.lm is not None and f < data.lm.n_frames:
                cells.append(f"{float(data.lm.confidence[f].mean()):.3f}")
            else:
                cells.append("")
            thumbs = [_img_tag(_png_img(source_thumb(data, frames, f, size=96)), f"source frame {number}")]
            if mesh_renderer is not None and f < data.n_character_frames:
                thumbs.append(_img_tag(_png_img(mesh_renderer.render(data.frame_vertices(f))),
                                       f"target frame {number}"))
            cells.append(_Raw(f'<span class="thumb">{"".join(thumbs)}</span>'))
            rows.append(cells)
        header = ["frame", "time (s)", "listed for"] + [f"residual {n}" for n in res] + ["jitter", "confidence",
                                                                                        "source | target"]
        nres = len(res)
        body += "<h3>Worst frames</h3>"
        body += (f'<p class="muted">Highest summed residual and highest summed jitter, at most {worst} each, '
                 f"at least {WORST_SUPPRESS + 1} frames apart.</p>")
        body += _table(header, rows, num_cols=tuple(range(0, 2)) + tuple(range(3, 5 + nres)))
    summ = [(n, f"{res[n].mean():.3g}" if n in res else "", f"{res[n].max():.3g}" if n in res else "",
             f"{jit[n].mean():.3g}") for n in data.regions]
    body = _table(("region", f"mean residual ({unit})", "max residual", "jitter score"), summ,
                  num_cols=(1, 2, 3)) + body
    return _section("residuals", "Residual and jitter per frame", body)


def find_truth(run: RunFiles, truth=None) -> tuple[Path | None, np.ndarray | None]:
    """The synthetic take's ``truth.npz`` and its true animation (T, N, 3), or ``(None, None)``.

    *truth* when given (a file without the true animation is an :class:`InputError`), else the
    ``truth.npz`` beside the run's video when it holds one (another file of that name is passed
    over with a warning).
    """

    if truth is not None:
        return Path(truth), load_truth_animation(truth)
    beside = None if run.video is None else Path(run.video).parent / "truth.npz"
    if beside is None or not beside.is_file():
        return None, None
    try:
        return beside, load_truth_animation(beside)
    except RetargetError as e:
        log.warning("no comparison with the truth: %s", e)
        return None, None


def _truth_mesh_rows(data: RunData, run: RunFiles, target: np.ndarray, notes: list):
    """The mesh row of the truth section and the per-frame error (or ``None`` with a note why not)."""

    if not data.n_character_frames:
        notes.append("The run has no frames (apply) to compare with the true animation.")
        return [], None
    head = (run.manifests.get("apply", {}).get("settings") or {}).get("head_motion", "none")
    if data.frame_files and head not in (None, "none"):
        notes.append(f"Meshes not compared: apply put head motion on them (head_motion {head}); the true "
                     "animation is in the character's own frame.")
        return [], None
    n_v = data.mesh().n_vertices
    if n_v != target.shape[1]:
        notes.append(f"Meshes not compared: the frames have {n_v} vertices, the true animation {target.shape[1]}.")
        return [], None
    n = data.n_character_frames
    rows, at = _truth_rows(data, n, len(target))  # the truth is indexed by the video's frame numbers
    if len(rows) < n or len(rows) < len(target):
        notes.append(f"Compared over {len(rows)} frames (frames {n}, truth {len(target)}).")
    if len(rows) < 2:
        notes.append("Meshes not compared: fewer than 2 of the run's frames are frames of the truth.")
        return [], None
    m = mesh_against_truth(np.stack([data.frame_vertices(t) for t in rows]), target[at])
    row = ("target mesh (apply's frames)", f"{m['error_mean']:.4g} ({m['error_pct']:.1f} % of the mean true "
           "displacement)", f"{m['jitter']:.3g}", f"{m['jitter_truth']:.3g}", f"{m['jitter_ratio']:.2f}×")
    return [row], m["error_per_frame"]


def _truth_rows(data: RunData, n: int, n_truth: int) -> tuple[np.ndarray, np.ndarray]:
    """The run's rows (of its first *n*) whose source frame is a row of the truth (*n_truth* frames, one per frame
    of the video), and those truth rows: a take tracked from ``start: 100, step: 2`` is compared with the truth's
    frames 100, 102, …"""
    numbers = data.numbers(n)
    rows = np.flatnonzero((numbers >= 0) & (numbers < n_truth))
    return rows, numbers[rows]


def _truth_landmark_rows(data: RunData, keys: dict, truth_lm) -> list:
    """Rows of the tracked (filtered and raw) and the reconstructed landmarks against the true landmarks."""

    lm = data.lm
    sel, at = _truth_rows(data, lm.n_frames, truth_lm.n_frames)
    rows = []
    if len(sel) < 2:
        return rows
    for label, P in (("landmarks (track)", lm.points), ("landmarks before the filter (points_raw)", lm.points_raw)):
        if P is not None and P.shape[1:] == truth_lm.points.shape[1:]:
            m = points_against_truth(P[sel], truth_lm.points[at])
            rows.append((label, f"{m['error_px']:.3g} px", f"{m['jitter']:.3g}", f"{m['jitter_truth']:.3g}",
                         f"{m['jitter_ratio']:.2f}×"))

    for name, d in sorted((data.other["meta"].get("diagnostics") or {}).items()):
        pts = keys.get(name, {}).get("points")
        if isinstance(d, dict) and "shape_jitter_px" in d and pts:
            truth_jit = mean_acceleration(truth_lm.stabilized[at][:, np.asarray(pts, dtype=np.int64)])
            if truth_jit > 0:
                rows.append((f"reconstructed landmarks, {name} (decompose)", "", f"{d['shape_jitter_px']:.3g}",
                             f"{truth_jit:.3g}", f"{d['shape_jitter_px'] / truth_jit:.2f}×"))
    return rows


def _truth(data: RunData, run: RunFiles, keys: dict, truth: Path | None, target) -> str | None:
    """Section: the run against a synthetic take's ground truth (``truth.npz``, ``truth_landmarks.npz``).

    *target* is the true animation (T, N, 3) read from *truth*.
    """

    if truth is None:
        return None
    notes: list = []
    rows, per_frame = _truth_mesh_rows(data, run, target, notes)
    lm_path = truth.parent / "truth_landmarks.npz"
    if data.lm is not None and lm_path.is_file():
        rows += _truth_landmark_rows(data, keys, load_landmarks(lm_path))
    body = (f'<p>Against the ground truth of the synthetic take: {html.escape(_show(truth))}. Jitter is the mean '
            "acceleration of the vertices or points (model units or px per frame²).</p>")
    body += _table(("quantity", "mean error", "jitter", "truth's jitter", "ratio"), rows, num_cols=(2, 3, 4))
    body += "".join(f'<p class="muted">{html.escape(n)}</p>' for n in notes)
    if per_frame is not None:
        fig, ax = _figure(9, 2.4)
        a = ax[0, 0]
        a.plot(np.arange(len(per_frame)), per_frame, lw=1, color="#c33")
        a.set_ylabel("mean vertex error")
        a.set_xlabel("frame")
        body += _figure_html(_png_fig(fig), "Mean vertex distance of apply's frames from the true animation, "
                                            "per frame.")
    return _section("truth", "Against the truth", body)


def _find_rig_metrics(data: RunData, run: RunFiles) -> dict:
    """Per-frame ``cardinality`` / ``objective`` arrays found in the run: ``{metric: {label: (T,)}}``."""

    found: dict = {"cardinality": {}, "objective": {}}

    def take(label, key, arr):
        for m in found:
            if (key == m or key.endswith("_" + m)) and np.ndim(arr) == 1 and len(arr) > 1:
                found[m][label] = np.asarray(arr, dtype=np.float64)

    for name, ex in data.extras.items():
        for k, v in ex.items():
            take(name, k, v)
    for k, v in data.other.items():
        if k != "meta":
            take(k.rsplit("_", 1)[0] if "_" in k else "solve", k, v)
    skip = {p.resolve() for p in (run.landmarks, run.weights) if p is not None}
    if run.root.is_dir():
        for p in sorted(run.root.glob("*.npz")):
            if p.resolve() in skip:
                continue
            try:
                arrays = load_npz(p)
            except (InputError, OSError, ValueError):
                continue
            for k, v in arrays.items():
                take(f"{p.stem}" if k in found else f"{p.stem}:{k.rsplit('_', 1)[0]}", k, v)
    return {m: v for m, v in found.items() if v}


def _rig(data: RunData, run: RunFiles) -> str | None:
    metrics = _find_rig_metrics(data, run)
    if not metrics:
        return None
    n = len(metrics)
    fig, ax = _figure(9, 0.8 + 2.0 * n, n, 1, sharex=True)
    for i, (m, series) in enumerate(sorted(metrics.items())):
        a = ax[i, 0]
        for label, v in sorted(series.items()):
            a.plot(np.arange(len(v)), v, lw=1, label=label)
        a.set_ylabel(m)
        a.legend(fontsize=8)
    ax[-1, 0].set_xlabel("frame")
    rows = [(m, label, f"{v.mean():.4g}", f"{v.max():.4g}") for m, s in sorted(metrics.items())
            for label, v in sorted(s.items())]
    body = _table(("metric", "series", "mean", "max"), rows, num_cols=(2, 3))
    body += _figure_html(_png_fig(fig), "Cardinality (weights above 0.01) and objective per frame, as stored by a "
                                        "rig solve or the decomposition (series: file or region).")
    return _section("rig", "Cardinality and objective", body)


def _coverage(run: RunFiles) -> str | None:
    """Per region, the rig sliders auto-pose drives, cannot drive and left at 0 by choice (its ``coverage.json``)."""
    if run.targets is None:
        return None
    path = run.targets.parent / COVERAGE_JSON
    if not path.is_file():
        return None
    try:
        cov = json.loads(path.read_text())
        regions = cov["regions"]
        rows = [(name, str(len(g["driven"])), ", ".join(g["cannot"]) or "-", ", ".join(g["excluded"]) or "-")
                for name, g in sorted(regions.items())]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("%s: not a coverage file (%s); the report leaves it out", path, exc)
        return None
    body = _table(("region", "driven", "cannot be driven", "left at 0 by choice"), rows, num_cols=(1,))
    body += (f"<p>Which of the rig's sliders the landmark path moves ({html.escape(_show(path))}): "
             f"{html.escape(str(cov.get('rule', '')))}. Driven: "
             + html.escape(", ".join(n for g in regions.values() for n in g["driven"]) or "-") + ".</p>")
    return _section("coverage", "Slider coverage", body)


# --------------------------------------------------------------------------- assembly


def read_neutral(run: RunFiles) -> tuple[dict | None, dict]:
    """The neutral keys.json records (or None), and each stage's (``results.neutral`` of its manifest)."""
    record = None
    if run.keys is not None:
        try:
            rec = json.loads(Path(run.keys).read_text(encoding="utf-8")).get("neutral")
            record = rec if isinstance(rec, dict) and isinstance(rec.get("frame"), int) else None
        except (OSError, ValueError, AttributeError):
            record = None
    stages = {}
    for stage, man in run.manifests.items():
        rec = (man.get("results") or {}).get("neutral") if isinstance(man.get("results"), dict) else None
        if isinstance(rec, dict) and isinstance(rec.get("frame"), int):
            stages[stage] = rec
    return record, stages


def _neutral_frame(run: RunFiles, data: RunData) -> int | None:
    """The neutral's row of the take (the row of its source frame)."""
    record, stages = read_neutral(run)
    rec = record or next(iter(stages.values()), None)
    return None if rec is None else _record_row(rec, data)


def _record_row(rec: dict, data: RunData) -> int | None:
    return data.row_of(int(rec["frame"]))


def _rest_pose(data: RunData, run: RunFiles, frames: dict, mesh_renderer) -> str | None:
    """Section: the neutral (rest) frame, as keys.json and the stage manifests record it, and why."""
    record, stages = read_neutral(run)
    rec = record or next(iter(stages.values()), None)
    if rec is None:
        return None
    f, row = int(rec["frame"]), _record_row(rec, data)
    body = f"<p>Neutral frame <b>{f}</b> ({html.escape(str(rec.get('source', '')))}): " \
           f"{html.escape(str(rec.get('reason', '')))}.</p>"
    if rec.get("at_rest") is False:
        body += ('<p><b>No frame of the take is at rest</b>: the least expressive one is the neutral, so the '
                 "character's rest is the actor's expression there. Film a calibration of the actor at rest "
                 "(track.neutral) or choose the frame (neutral_frame).</p>")
    rows = [(stage, r["frame"], r.get("source", ""), "" if r.get("reason") == rec.get("reason") else r.get("reason", ""))
            for stage, r in stages.items()]
    if rows:
        body += _table(("stage", "neutral frame", "source", "why (when not as above)"), rows, num_cols=(1,))
        if len({r["frame"] for r in stages.values()}) > 1:
            body += "<p><b>The stages used different neutral frames.</b></p>"
    import cv2

    if row is None:
        body += f"<p>Frame {f} is not a frame of this take.</p>"
        return _section("rest", "Rest pose", body)
    tiles = [_label(source_thumb(data, frames, row), f"source {f}")]
    what = "the source frame"
    if mesh_renderer is not None and row < data.n_character_frames:
        img = cv2.resize(mesh_renderer.render(data.frame_vertices(row)), (THUMB, THUMB),
                         interpolation=cv2.INTER_AREA)
        tiles.append(_label(img, f"character {f}"))
        what += " and the character there (at rest when the neutral is)"
    body += _figure_html(_png_img(np.hstack(tiles)), f"Neutral frame {f}: {what}.")
    return _section("rest", "Rest pose", body)


def _read_keys_lenient(path: Path | None) -> dict:
    if path is None:
        return {}
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        regions = data.get("regions") or {}
        return {str(k): v for k, v in regions.items() if isinstance(v, dict)}
    except (OSError, json.JSONDecodeError, AttributeError) as exc:
        log.warning("%s: keys not read (%s)", path, exc)
        return {}


SECTION_TITLES = {
    "summary": "Run summary", "tracking": "Tracking confidence", "rest": "Rest pose", "keys": "Key shapes",
    "curve": "Reconstruction error against k", "weights": "Weight curves",
    "residuals": "Residual and jitter per frame", "rig": "Cardinality and objective",
    "truth": "Against the truth", "coverage": "Slider coverage",
}


def build_report(run: RunFiles, *, worst: int = 6, camera=None, shading: str = "gouraud", progress=None,
                 truth=None) -> str:
    """The report's HTML text (deterministic for the same run).

    Parameters
    ----------
    run : RunFiles
    worst : int
        Worst frames listed per criterion (residual, jitter).
    camera : retarget_cli.methods.render.Camera, optional
    shading : {"gouraud", "flat"}
    progress : callable, optional
        ``progress(length, label)`` context manager.
    truth : path-like, optional
        A synthetic take's ``truth.npz`` (default: the one beside the run's video, when there is one).
    """

    _matplotlib()  # fail early, before any work, when the extra is missing
    truth, target = find_truth(run, truth)  # a bad --truth file fails before the work
    camera = camera or Camera()
    data = RunData(run)
    keys = _read_keys_lenient(run.keys)
    need = set()
    for reg in _sheet_regions(data, keys).values():
        need |= {r for r in reg["rows"][:MAX_SHEET_KEYS] if r is not None}
    neutral = _neutral_frame(run, data)
    if neutral is not None:
        need.add(neutral)
    mesh_renderer = None
    mesh = data.mesh()
    if mesh is not None:
        mesh_renderer = MeshRenderer(mesh.faces(), mesh.vertices, camera=camera, size=(96, 96), shading=shading)
    if data.regions:
        # the frames the residual section will list (computed the same way there)
        res = _residual_rms(data, keys)
        T = next(iter(data.regions.values()))[0].shape[0]
        if res:
            need |= set(worst_frames(np.sum([r[:T] for r in res.values()], axis=0), worst))
        need |= set(worst_frames(np.sum([jitter_per_frame(W) if data.extras.get(n, {}).get("jitter") is None
                                         or np.shape(data.extras[n]["jitter"]) != (T,)
                                         else np.asarray(data.extras[n]["jitter"], dtype=np.float64)
                                         for n, (W, _) in data.regions.items()], axis=0), worst))
    steps = ["frames", "summary", "tracking", "rest", "keys", "curve", "coverage", "weights", "residuals", "rig", "truth"]
    bar_cm = progress(len(steps), "report") if progress else nullcontext(None)
    sections = []
    with bar_cm as bar:
        def done():
            if bar:
                bar.update(1)

        frames = grab_frames(run.video, need, data.numbers(data.n_frames))
        done()
        summary, _ = _summary(data, run, keys)
        sections.append(summary)
        done()
        for fn in (lambda: _tracking(data),
                   lambda: _rest_pose(data, run, frames, mesh_renderer),
                   lambda: _keys_sheet(data, run, keys, frames, camera, shading),
                   lambda: _curve(run, keys),
                   lambda: _coverage(run),
                   lambda: _weights(data),
                   lambda: _residuals(data, keys, frames, worst, mesh_renderer),
                   lambda: _rig(data, run),
                   lambda: _truth(data, run, keys, truth, target)):
            s = fn()
            if s:
                sections.append(s)
            done()
    ids = [s.split('"', 2)[1] for s in sections]
    nav = " ".join(f'<a href="#{i}">{html.escape(SECTION_TITLES.get(i, i))}</a>' for i in ids)
    title = f"retarget report: {run.root.name or run.root}"

    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<meta name=\"generator\" content=\"retarget {html.escape(__version__)}\">\n"
            f"<title>{html.escape(title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n"
            f"<header><h1>{html.escape(title)}</h1><nav>{nav}</nav></header>\n"
            + "\n".join(sections) + "\n</body>\n</html>\n")


def write_report(run: RunFiles, output: str | os.PathLike, **kw) -> Path:
    """Write :func:`build_report`'s HTML to *output* atomically; returns *output*."""

    check_not_input(output, [run.landmarks, run.weights, run.keys, run.video, kw.get("truth")])
    text = build_report(run, **kw)
    write_text(output, text)
    log.info("wrote %s (%.1f MB)", output, len(text) / 1e6)
    return Path(output)

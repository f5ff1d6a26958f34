"""Files of the rig-editing commands: rig animations (CSV or NPZ) and ``edits.yaml``.

Formats are documented in the README's "Rig editing" section.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

from .. import __version__
from .._validate import closest
from ..config import load_yaml, unknown_key_error
from ..errors import InputError
from ..methods.editing import DEFAULT_ALPHA, DEFAULT_MU, AttenuateEdit, Pin, PinEdit
from ..methods.rig import parse_axes
from .atomic import atomic_open, load_npz, savez
from .stagefiles import read_vertex_mask
from .text import read_text

# --------------------------------------------------------------------------- animations


#: The head's columns of a curves CSV (:func:`write_animation`): yaw, pitch, roll in degrees and the translation.
HEAD_COLUMNS = ("head_yaw", "head_pitch", "head_roll", "head_x", "head_y", "head_z")


def read_animation(path: str | os.PathLike) -> tuple[list, np.ndarray, np.ndarray, np.ndarray | None]:
    """Read rig weights over time.

    CSV: a header with ``frame``, optionally ``time``, and one column per
    slider; frames are strictly increasing integers. NPZ: ``curves`` (T, E)
    and ``names`` (E,) (what ``retarget synth`` writes as ``truth.npz``),
    optionally ``frames`` (T,) and ``times`` (T,); other members are ignored.

    Returns
    -------
    names : list of str
    W : ndarray, shape (T, E)
    frames : ndarray, shape (T,), int64
    times : ndarray, shape (T,) or None
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: animation file not found")
    times = None
    if path.suffix.lower() == ".npz":
        data = load_npz(path)
        if "curves" not in data or "names" not in data:
            raise InputError(f"{path}: expected 'curves' (T, E) and 'names' (E,)")
        W, names = np.asarray(data["curves"], dtype=np.float64), [str(n) for n in data["names"]]
        if W.ndim != 2 or W.shape[1] != len(names):
            raise InputError(f"{path}: 'curves' must be (T, {len(names)}) for {len(names)} names, got {W.shape}")
        frames = np.asarray(data.get("frames", np.arange(len(W))), dtype=np.int64)
        if "times" in data:
            times = np.asarray(data["times"], dtype=np.float64)
            if times.shape != (len(W),):
                raise InputError(f"{path}: 'times' must be ({len(W)},), one per row, got {times.shape}")
    elif path.suffix.lower() == ".csv":

        header, rows = _csv_table(path, read_text(path, "animation CSV"))
        fcol = rows[:, header.index("frame")]
        if np.any(fcol % 1 != 0):
            raise InputError(f"{path}: 'frame' values must be integers")
        frames = fcol.astype(np.int64)
        if "time" in header:
            times = rows[:, header.index("time")]
        names = [h for h in header if h not in ("frame", "time", "found", *HEAD_COLUMNS)]
        W = rows[:, [header.index(n) for n in names]]
    else:
        raise InputError(f"{path}: expected a .csv or .npz animation")
    if len(set(names)) != len(names):
        raise InputError(f"{path}: slider names repeat")
    if frames.shape != (len(W),) or np.any(np.diff(frames) <= 0):
        raise InputError(f"{path}: frames must be strictly increasing, one per row")
    if not np.all(np.isfinite(W)):
        t = int(np.argwhere(~np.isfinite(W))[0, 0])
        raise InputError(f"{path}: frame {int(frames[t])} has a non-finite weight")
    return names, W, frames, times


def _csv_table(path: Path, text: str) -> tuple[list, np.ndarray]:
    """The header (stripped names; quoted as CSV quotes them) and the numbers of an animation CSV.

    Raises
    ------
    InputError
        Naming the file and the line of a row that is short, long or holds something that is not a number.
    """
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise InputError(f"{path}: empty CSV")
    header = [h.strip() for h in next(csv.reader([lines[first]]))]
    if "frame" not in header:
        raise InputError(f"{path}: the header needs a 'frame' column, got {','.join(header)}")
    # each row parsed into its place: a long take's rows are never held as lists of Python floats (~2 KB a row)
    rows, n = np.empty((len(lines) - first - 1, len(header))), 0
    for lineno in range(first + 2, len(lines) + 1):
        ln = lines[lineno - 1]
        if not ln.strip():
            continue
        cells = ln.split(",")
        if len(cells) != len(header):
            raise InputError(f"{path}:{lineno}: {len(cells)} values, expected {len(header)} (one per header column)")
        try:
            rows[n] = [float(x) for x in cells]
        except ValueError:
            bad = next(x for x in cells if not _is_number(x))
            raise InputError(f"{path}:{lineno}: {bad.strip()[:40]!r} is not a number") from None
        n += 1
    if not n:
        raise InputError(f"{path}: no rows after the header")
    return header, rows[:n] if n < len(rows) else rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_animation(path: str | os.PathLike, names, W, frames, times=None, *, meta: dict | None = None,
                    found=None, head=None) -> None:
    """Write rig weights over time, CSV or NPZ by the file's extension (the formats of :func:`read_animation`).

    *found* (T,) bool, optional: whether the face was found in each frame (a take with gaps): a ``found``
    column of 0/1 after ``frame``/``time`` in a CSV (:func:`read_animation` skips it), a ``found`` member of
    an NPZ. *head* (T, 6), optional: the head's yaw, pitch, roll (degrees) and translation x, y, z
    (``landmarks.npz``'s ``head_angles``, ``head_translation``): the :data:`HEAD_COLUMNS` after the sliders in
    a CSV (:func:`read_animation` skips them), ``head_angles`` (T, 3) and ``head_translation`` (T, 3) members
    of an NPZ.
    """
    path = Path(path)
    W = np.asarray(W, dtype=np.float64)
    H = None if head is None else np.asarray(head, dtype=np.float64)
    if H is not None and H.shape != (len(W), 6):
        raise InputError(f"{path}: head: expected shape ({len(W)}, 6), got {H.shape}")
    if path.suffix.lower() == ".npz":
        arrays = {"curves": W, "names": np.asarray(names, dtype=str), "frames": np.asarray(frames, dtype=np.int64),
                  "meta": np.array(json.dumps({"version": __version__, **(meta or {})}, sort_keys=True))}
        if times is not None:
            arrays["times"] = np.asarray(times, dtype=np.float64)
        if found is not None:
            arrays["found"] = np.asarray(found, dtype=bool)
        if H is not None:
            arrays["head_angles"], arrays["head_translation"] = H[:, :3], H[:, 3:]
        savez(path, arrays)
        return
    if path.suffix.lower() != ".csv":
        raise InputError(f"{path}: expected a .csv or .npz output")
    head = ["frame"] + (["time"] if times is not None else []) + (["found"] if found is not None else []) + list(names)
    head += list(HEAD_COLUMNS) if H is not None else []
    if H is not None:
        W = np.concatenate([W, H], axis=1)
    line = io.StringIO()
    csv.writer(line, lineterminator="").writerow(head)  # a name holding a comma or a quote is quoted
    # streamed a row at a time: a long take's text is never held whole
    with atomic_open(path, "w") as fh:
        fh.write(line.getvalue() + "\n")
        for t, f in enumerate(frames):
            cells = [str(int(f))] + ([f"{times[t]:.6f}"] if times is not None else []) + \
                ([str(int(bool(found[t])))] if found is not None else []) + [f"{v:.6f}" for v in W[t]]
            fh.write(",".join(cells) + "\n")


# --------------------------------------------------------------------------- edits.yaml

EDIT_KINDS = ("pin", "attenuate")
COMMON_KEYS = ("frames", "ease_in", "ease_out", "solve")
PIN_KEYS = COMMON_KEYS + ("alpha", "mu", "w0", "constraints")
ATTENUATE_KEYS = COMMON_KEYS + ("alpha", "reference", "select")
CONSTRAINT_KEYS = ("vertex", "axes", "weight", "position", "offset", "frame", "to_vertex")
SELECT_KEYS = ("vertices", "axes")


def _int(value, where, minimum=None):
    if isinstance(value, bool) or not isinstance(value, int) or (minimum is not None and value < minimum):
        more = f" >= {minimum}" if minimum is not None else ""
        raise InputError(f"{where}: expected an integer{more}, got {value!r}")
    return value


def _num(value, where, minimum=None):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or (minimum is not None and value < minimum):
        more = f" >= {minimum:g}" if minimum is not None else ""
        raise InputError(f"{where}: expected a finite number{more}, got {value!r}")
    return float(value)


def _vec3(value, where):
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(f"{where}: expected [x, y, z], got {value!r}")
    return tuple(_num(v, where) for v in value)


def _axes(value, where):
    try:
        parse_axes(value)
    except ValueError:
        raise InputError(f"{where}: expected a combination of x, y, z such as 'xy', got {value!r}") from None
    return value


def _keys(d, valid, where):
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a mapping, got {d!r}")
    for k in d:
        if k not in valid:
            raise unknown_key_error(where, str(k), valid, error=InputError)


def _vertex(value, where, n_vertices):
    _int(value, where)
    if not 0 <= value < n_vertices:
        raise InputError(f"{where}: vertex {value} is outside the mesh ({n_vertices} vertices, ids 0-{n_vertices - 1})")
    return value


def _frame(value, where, frames):
    _int(value, where)
    if value not in frames:
        raise InputError(f"{where}: frame {value} is not in the animation (frames {frames[0]}-{frames[-1]})")
    return value


def _load_edits_yaml(path: Path):
    data = load_yaml(read_text(path, "edits"), str(path), error=InputError)
    _keys(data, ("rig", "edits"), str(path))
    if "rig" in data and not isinstance(data["rig"], str):
        raise InputError(f"{path}: rig: expected the path of a rig.yaml, got {data['rig']!r}")
    return data


def edits_rig(path: str | os.PathLike) -> Path | None:
    """The ``rig:`` of an ``edits.yaml`` (relative to the file), or None."""
    path = Path(path)
    rig = _load_edits_yaml(path).get("rig")
    return path.parent / rig if rig else None


def _edit_body(item, where: str) -> tuple[str, dict, str]:
    """``(kind, settings, where.kind)`` of one ``edits[i]`` entry (``{pin: {...}}`` or ``{attenuate: {...}}``)."""
    if not isinstance(item, dict) or len(item) != 1:
        raise InputError(f"{where}: expected one of 'pin:' or 'attenuate:' with its settings")
    kind, body = next(iter(item.items()))
    if kind not in EDIT_KINDS:
        raise unknown_key_error(where, str(kind), EDIT_KINDS, error=InputError)
    where = f"{where}.{kind}"
    _keys(body, PIN_KEYS if kind == "pin" else ATTENUATE_KEYS, where)
    return kind, body, where


def _edit_common(body: dict, where: str, frames: list) -> dict:
    """The settings every edit has: frame range, ease in / out, solve; checked against the animation."""
    fr = body.get("frames")
    if isinstance(fr, int) and not isinstance(fr, bool):
        fr = [fr, fr]
    if not isinstance(fr, list) or len(fr) != 2 or not all(isinstance(f, int) and not isinstance(f, bool)
                                                           for f in fr) or fr[0] > fr[1]:
        raise InputError(f"{where}.frames: expected a frame or [first, last] (inclusive), got {fr!r}")
    ease_in = _int(body.get("ease_in", 0), f"{where}.ease_in", 0)
    ease_out = _int(body.get("ease_out", 0), f"{where}.ease_out", 0)
    if fr[1] + ease_out < frames[0] or fr[0] - ease_in > frames[-1]:
        raise InputError(f"{where}.frames: {fr} is outside the animation (frames {frames[0]}-{frames[-1]})")
    solve = body.get("solve", "bounded")
    if solve not in ("bounded", "closed-form"):
        hint = closest(str(solve), ("bounded", "closed-form"))
        raise InputError(f"{where}.solve: expected 'bounded' or 'closed-form', got {solve!r}"
                          + (f"; did you mean {hint!r}?" if hint else ""))
    return dict(frames=(fr[0], fr[1]), ease_in=ease_in, ease_out=ease_out, bounded=solve == "bounded",
                where=where)


def _pin(c, cw: str, n_vertices: int, frames: list):
    """One ``constraints[j]`` entry of a pin edit as a :class:`~retarget_cli.methods.editing.Pin`."""

    _keys(c, CONSTRAINT_KEYS, cw)
    if "vertex" not in c:
        raise InputError(f"{cw}: 'vertex' is required")
    if "position" in c and any(k in c for k in ("offset", "frame", "to_vertex")):
        raise InputError(f"{cw}: 'position' is absolute; it cannot be combined with offset, frame or to_vertex")
    return Pin(
        vertex=_vertex(c["vertex"], f"{cw}.vertex", n_vertices),
        axes=_axes(c.get("axes", "xyz"), f"{cw}.axes"),
        weight=_num(c.get("weight", 1.0), f"{cw}.weight", 0.0),
        position=_vec3(c["position"], f"{cw}.position") if "position" in c else None,
        offset=_vec3(c["offset"], f"{cw}.offset") if "offset" in c else (0.0, 0.0, 0.0),
        frame=_frame(c["frame"], f"{cw}.frame", frames) if "frame" in c else None,
        to_vertex=_vertex(c["to_vertex"], f"{cw}.to_vertex", n_vertices) if "to_vertex" in c else None,
    )


def _w0(w0, where: str, expressions) -> dict | None:
    """A pin edit's ``w0``: None for ``current``, else ``{expression: coefficient}`` of known expressions."""
    if w0 == "current":
        return None
    if not (isinstance(w0, dict) and w0):
        raise InputError(f"{where}.w0: expected 'current' or {{expression: coefficient}}, got {w0!r}")
    for name, coef in w0.items():
        if name not in expressions:
            hint = closest(str(name), expressions)
            known = ", ".join(expressions) or "no expressions"
            raise InputError(f"{where}.w0: unknown expression {name!r}"
                              + (f"; did you mean {hint!r}?" if hint else f"; the rig's library has {known}"))
        _num(coef, f"{where}.w0.{name}")
    return {str(k): float(v) for k, v in w0.items()}


def _pin_edit(body: dict, common: dict, n_vertices: int, frames: list, expressions):
    """A ``pin:`` edit's settings as a :class:`~retarget_cli.methods.editing.PinEdit`."""

    where = common["where"]
    cons = body.get("constraints")
    if not isinstance(cons, list) or not cons:
        raise InputError(f"{where}.constraints: expected a non-empty list of {{vertex: id, position: [x, y, z]}}")
    pins = [_pin(c, f"{where}.constraints[{j}]", n_vertices, frames) for j, c in enumerate(cons)]
    w0 = _w0(body.get("w0", "current"), where, expressions)
    edit = PinEdit(pins=pins, alpha=_num(body.get("alpha", DEFAULT_ALPHA), f"{where}.alpha", 0.0),
                   mu=_num(body.get("mu", DEFAULT_MU), f"{where}.mu", 0.0), w0=w0, **common)
    if edit.alpha + edit.mu <= 0:
        raise InputError(f"{where}: alpha + mu must be > 0")
    return edit


def _select_group(g, gw: str, path: Path, n_vertices: int) -> tuple[list, str]:
    """One ``select[j]`` entry of an attenuate edit: ``(vertex ids, axes)``; a string names a vertex-mask file."""

    _keys(g, SELECT_KEYS, gw)
    verts = g.get("vertices")
    if isinstance(verts, str):
        mask_file = path.parent / verts
        verts = [int(v) for v in np.flatnonzero(read_vertex_mask(mask_file, n_vertices) > 0)]
        if not verts:
            raise InputError(f"{gw}.vertices: {mask_file} selects no vertex")
    if not isinstance(verts, list) or not verts:
        raise InputError(f"{gw}.vertices: expected a list of vertex ids or a vertex-mask file")
    verts = [_vertex(v, f"{gw}.vertices", n_vertices) for v in verts]
    return verts, _axes(g.get("axes", "xyz"), f"{gw}.axes")


def _attenuate_edit(body: dict, common: dict, path: Path, n_vertices: int, frames: list):
    """An ``attenuate:`` edit's settings as an :class:`~retarget_cli.methods.editing.AttenuateEdit`."""

    where = common["where"]
    sel = body.get("select")
    if not isinstance(sel, list) or not sel:
        raise InputError(f"{where}.select: expected a non-empty list of {{vertices: [ids], axes: xyz}}")
    groups = [_select_group(g, f"{where}.select[{j}]", path, n_vertices) for j, g in enumerate(sel)]
    ref = body.get("reference", "start")
    if ref not in ("start", "neutral"):
        _frame(ref, f"{where}.reference", frames)
    alpha = body.get("alpha")
    alpha = None if alpha is None else _num(alpha, f"{where}.alpha", 0.0)
    return AttenuateEdit(select=groups, alpha=alpha, reference=ref, **common)


def read_edits(path: str | os.PathLike, *, n_vertices: int, frames, expressions=()) -> list:
    """Read and check ``edits.yaml`` against a rig and an animation.

    Parameters
    ----------
    n_vertices : int
        The rig's vertex count (pin and selection ids must lie below it).
    frames : sequence of int
        The animation's frames (edit ranges must overlap them).
    expressions : sequence of str
        The rig library's expression names (for ``w0``).

    Returns
    -------
    list of :class:`~retarget_cli.methods.editing.PinEdit` and :class:`~retarget_cli.methods.editing.AttenuateEdit`

    Raises
    ------
    InputError
        Naming the file, the edit (``edits[2].pin.constraints[0].vertex``) and
        what was expected; unknown keys get the closest valid key.
    """
    path = Path(path)
    data = _load_edits_yaml(path)
    frames = [int(f) for f in frames]
    items = data.get("edits")
    if not isinstance(items, list) or not items:
        raise InputError(f"{path}: edits: expected a non-empty list of '- pin: {{...}}' or '- attenuate: {{...}}'")
    out = []
    for i, item in enumerate(items):
        kind, body, where = _edit_body(item, f"{path}: edits[{i}]")
        common = _edit_common(body, where, frames)
        if kind == "pin":
            out.append(_pin_edit(body, common, n_vertices, frames, expressions))
        else:
            out.append(_attenuate_edit(body, common, path, n_vertices, frames))
    return out


__all__ = ["HEAD_COLUMNS", "edits_rig", "read_animation", "read_edits", "write_animation"]

"""``map-landmarks``: find the rig vertex of each of the 68 tracked landmarks (the rig's ``landmarks:``).

Reads a rig (``rig.yaml``, through :func:`~retarget_cli.io.rig.load_rig`),
renders its neutral face-on, places the 68 points with the pretrained
detector and lifts them to the mesh, or places them from the sliders when no
face is found (:func:`retarget_cli.methods.landmark_map.find_landmark_map`).
Writes the map (one vertex id per line, as ``landmarks: file`` and
``--landmark-vertices`` read it), optionally a contact sheet with the
numbered points, and prints the map's quality. ``--points`` corrects points
by hand. ``auto-pose`` runs the same step when the rig has no map
(:func:`cached_landmark_map`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..config import Command, Flag, Param, output_flag, validate_params
from ..errors import InputError, MissingExtraError
from ..io.atomic import check_not_input, digest_files, write_bytes, write_text
from ..io.face_detector import face_detector_file
from ..io.rig import load_rig, read_rig
from ..methods import landmark_map as lm
from ..methods.tracking.detect import Detector, detector_installed
from ._common import NO_CACHE, NO_CACHE_FLAG, _require, command_cache_dir

log = logging.getLogger(__name__)

#: Declared parameters of ``map_landmarks`` (CLI options, docs/config.md).
PARAMS = [
    Param("rig", "input", str, help="rig.yaml (its neutral and sliders)."),
    Param("output", "output", str, help="The map: one rig vertex id per line, landmark 0 first."),
    Param("sheet", "output", str, None, "Contact sheet PNG: the render with the 68 numbered points.", nullable=True),
    Param("points", "input", str, None,
          "Corrections: lines 'index vertex' or 'index x y' (pixels of the contact sheet).", nullable=True),
    Param("yaw", "setting", float, None,
          "Camera yaw in degrees that shows the face (0: it looks along +z, 180: along -z); default from the mesh.",
          min=-360, max=360, nullable=True),
]

#: Header line of a map file that records the rig's digest (auto-pose reuses a map while it matches).
DIGEST_PREFIX = "# rig sha256 "


def rig_arrays(rig):
    """(neutral (N, 3), faces, deltas (n, N, 3), names) of a :class:`~retarget_cli.methods.rig.BlendshapeRig`.

    The faces come from the rig's ``faces`` if it has them, else its template's (an OBJ's ``faces()``).
    """
    faces = getattr(rig, "faces", None)
    if faces is None:
        t = rig.template
        if t is None:
            raise InputError("the rig has no faces to render (no template mesh)")
        faces = t.faces() if callable(getattr(t, "faces", None)) else t.faces
    D = rig.D.toarray() if hasattr(rig.D, "toarray") else np.asarray(rig.D)
    deltas = D.T.reshape(rig.n_sliders, rig.n_vertices, 3)
    return rig.neutral, faces, deltas, list(rig.names)


def _detector():
    """The pretrained detector, or None (with a warning) when the ``detect`` extra is not installed."""
    if not detector_installed():
        log.warning("map-landmarks: the detector is not installed (pip install 'retarget[detect]'); "
                    "placing the landmarks from the sliders")
        return None
    try:
        return Detector(faces_file=face_detector_file())
    except MissingExtraError as exc:
        log.warning("map-landmarks: %s; placing the landmarks from the sliders", exc)
        return None


def find_map(rig, *, yaw=None, detector="auto") -> lm.LandmarkMap:
    """:func:`~retarget_cli.methods.landmark_map.find_landmark_map` on a loaded rig (*detector* "auto": dlib's)."""
    V, F, D, names = rig_arrays(rig)
    det = _detector() if detector == "auto" else detector
    return lm.find_landmark_map(V, F, D, names, detector=det, yaw=yaw)


def read_points(path, n_vertices: int, size) -> tuple[dict, dict]:
    """Corrections file: ``index vertex`` or ``index x y`` lines (``#`` comments) -> (vertex fixes, pixel fixes).

    Pixels are the contact sheet's (:func:`~retarget_cli.methods.landmark_map.draw_sheet`) and are
    returned in the render's pixels; *size* is the sheet's (width, height).

    Raises
    ------
    InputError
        ``file:line`` for a line that is neither, a landmark outside 0-67 or given twice, a vertex outside
        the mesh, a pixel outside the sheet.
    """
    path = _require(path, "points file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    vertex, pixel, seen = {}, {}, {}
    for no, line in enumerate(text.splitlines(), 1):
        tok = line.split("#", 1)[0].replace(",", " ").split()
        if not tok:
            continue
        where = f"{path}:{no}"
        try:
            nums = [int(tok[0])] + [float(t) for t in tok[1:]]
        except ValueError:
            nums = None
        if nums is None or len(tok) not in (2, 3):
            raise InputError(f"{where}: expected 'index vertex' or 'index x y', got {line.strip()!r}")
        i = nums[0]
        if not 0 <= i < lm.N_POINTS:
            raise InputError(f"{where}: landmark {i} does not exist (landmarks 0-{lm.N_POINTS - 1})")
        if i in seen:
            raise InputError(f"{where}: landmark {i} is corrected twice (also on line {seen[i]})")
        seen[i] = no
        if len(tok) == 2:
            if not tok[1].lstrip("-").isdigit() or not 0 <= int(tok[1]) < n_vertices:
                raise InputError(f"{where}: vertex {tok[1]} is outside the mesh ({n_vertices} vertices, "
                                 f"ids 0-{n_vertices - 1})")
            vertex[i] = int(tok[1])
        else:
            x, y = nums[1], nums[2]
            if not (np.isfinite(x) and np.isfinite(y) and 0 <= x < size[0] and 0 <= y < size[1]):
                raise InputError(f"{where}: pixel ({tok[1]}, {tok[2]}) is outside the contact sheet "
                                 f"({size[0]}x{size[1]})")
            pixel[i] = tuple(lm.points_from_sheet([[x, y]])[0])
    return vertex, pixel


def map_text(lmap: lm.LandmarkMap, rig_name: str, digest: str | None = None) -> str:
    """The map file: a header, then one vertex id per line with the landmark, region and source as a comment."""
    region = {i: name for name, ids in lm.REGIONS_68.items() for i in ids}
    how = "the sliders (no face found by the detector)" if lmap.found_by == "sliders" else \
        f"the detector on the {lmap.found_by!r} render"
    lines = [f"# Landmark map of {rig_name}: the rig vertex of each of the 68 Multi-PIE landmarks, in order,",
             f"# found by retarget map-landmarks from {how}, yaw {lmap.render.yaw:.1f}. Check the contact sheet."]
    if digest:
        lines.append(DIGEST_PREFIX + digest)
    lines += [f"{int(v)}  # {i} {region[i]} {s}" for i, (v, s) in enumerate(zip(lmap.vertices, lmap.source))]
    return "\n".join(lines) + "\n"


def write_sheet(path, lmap: lm.LandmarkMap, title: str) -> None:
    """The contact sheet PNG (no metadata: the same bytes for the same map)."""
    import cv2

    ok, buf = cv2.imencode(".png", lm.draw_sheet(lmap, title))
    if not ok:
        raise InputError(f"{path}: OpenCV cannot write this image")
    write_bytes(path, buf.tobytes())


def quality(rig, lmap: lm.LandmarkMap) -> dict:
    """:func:`~retarget_cli.methods.landmark_map.map_quality` of *lmap* on *rig*, with how it was found."""
    q = lm.map_quality(rig.neutral, lmap.vertices, yaw=lmap.render.yaw, source=lmap.source)
    q.update(found_by=lmap.found_by, tried=list(lmap.tried), yaw=lmap.render.yaw)
    return q


def summary_lines(q: dict) -> list[str]:
    """The quality summary as printed lines."""
    a, b = q["worst_pair"]
    how = "sliders (the detector found no face on: " + ", ".join(q["tried"]) + ")" if q["found_by"] == "sliders" \
        and q["tried"] else q["found_by"]
    lines = [f"found by: {how}; yaw {q['yaw']:.1f} degrees",
             f"inter-ocular distance (points 36-45): {q['iod']:.4g} rig units",
             f"left/right symmetry: mean {q['symmetry_mean']:.3f}, max {q['symmetry_max']:.3f} inter-ocular "
             f"distances (worst pair {a}/{b})"]
    total: dict = {}
    for by in q["regions"].values():
        for src, n in by.items():
            total[src] = total.get(src, 0) + n
    lines.append("points by source: " + ", ".join(f"{n} {s}" for s, n in sorted(total.items())))
    for region, by in q["regions"].items():
        lines.append(f"  {region:<11} " + ", ".join(f"{n} {s}" for s, n in sorted(by.items())))
    if q["shared"]:
        lines.append("landmarks on one vertex: " + "; ".join("/".join(map(str, ids)) for ids in q["shared"]))
    else:
        lines.append("no two landmarks on one vertex")
    return lines


@validate_params(PARAMS)
def run_map_landmarks(*, rig, output, sheet=None, points=None, yaw=None, cache_dir=None, detector="auto") -> dict:
    """Find the landmark map of *rig*; write it to *output* (and the contact sheet to *sheet*).

    Returns
    -------
    dict
        ``written`` (paths), ``quality`` (:func:`quality`).
    """
    rig_path = _require(rig, "rig file")
    spec = read_rig(rig_path)
    inputs = [rig_path, *spec.files()] + ([points] if points else [])
    for out in filter(None, (output, sheet)):
        check_not_input(out, inputs)
    if sheet is not None and Path(sheet).suffix.lower() != ".png":
        raise InputError(f"{sheet}: the contact sheet is a PNG (name it .png)")
    r = load_rig(rig_path, cache_dir=cache_dir)
    lmap = find_map(r, yaw=yaw, detector=detector)
    if points is not None:
        H, W = lmap.render.image.shape[:2]
        size = (W * lm.SHEET_SCALE, H * lm.SHEET_SCALE)
        fix_v, fix_p = read_points(points, r.n_vertices, size)
        lmap = lm.correct(lmap, fix_v, fix_p)
    write_text(output, map_text(lmap, Path(rig_path).name))
    written = [Path(output)]
    if sheet is not None:
        write_sheet(sheet, lmap, Path(rig_path).name)
        written.append(Path(sheet))
    return {"written": written, "quality": quality(r, lmap)}


def cached_landmark_map(rig_path, rig, spec, folder) -> Path:
    """The map of a rig with no ``landmarks:``, found once and kept as ``folder/landmark_map.txt``.

    Reused while its recorded digest equals the digest of ``rig.yaml`` and
    its meshes; written anew (with ``landmark_map.png``, its contact sheet)
    otherwise. Logs a warning that names the sheet to check.
    """
    folder = Path(folder)
    path, sheet = folder / "landmark_map.txt", folder / "landmark_map.png"
    digest = digest_files([rig_path, *spec.files()])
    if path.is_file():
        head = path.read_text(encoding="utf-8", errors="replace").splitlines()[:4]
        if DIGEST_PREFIX + digest in head:
            log.info("auto-pose: the rig has no landmarks:; using %s, found earlier for this rig", path)
            return path
    lmap = find_map(rig)
    folder.mkdir(parents=True, exist_ok=True)
    write_text(path, map_text(lmap, Path(rig_path).name, digest))
    write_sheet(sheet, lmap, Path(rig_path).name)
    q = quality(rig, lmap)
    log.warning("auto-pose: %s has no landmarks:; found them automatically (%s; symmetry mean %.3f inter-ocular "
                "distances): %s. Check the points on %s and correct them with retarget map-landmarks --points",
                rig_path, "from the sliders" if lmap.found_by == "sliders" else f"detector, {lmap.found_by} render",
                q["symmetry_mean"], path, sheet)
    return path


def _cli_map_landmarks(values, out):
    kw = dict(values)
    cache_dir = command_cache_dir(kw["output"], kw.pop("no_cache"))
    return run_map_landmarks(**kw, cache_dir=cache_dir)


def _show_map_landmarks(result, out) -> None:
    for p in result["written"]:
        out.echo(str(p))
    for line in summary_lines(result["quality"]):
        out.echo(line)


#: ``map-landmarks`` (the CLI builds it: :mod:`retarget_cli.cli.commands`).
COMMAND = Command(
    "map-landmarks",
    """Find the rig vertex of each of the 68 tracked landmarks of RIG: the map rig.yaml's 'landmarks:' names.

    Renders the neutral face-on, places the points with the pretrained
    detector and lifts them to the mesh (or places them from the blink,
    jaw-open, smile and brow sliders when no face is found). Check the
    contact sheet (--sheet) and correct points with --points.
    """,
    lambda: [*PARAMS, NO_CACHE],
    (Flag("rig", argument=True, path="file"),
     output_flag(None, "The map: one rig vertex id per line, landmark 0 first."),
     Flag("sheet", path="file", show_default=False), Flag("points", path="file", show_default=False),
     Flag("yaw", show_default=False), NO_CACHE_FLAG),
    _cli_map_landmarks,
    _show_map_landmarks,
)

__all__ = ["COMMAND", "PARAMS", "cached_landmark_map", "find_map", "map_text", "read_points", "rig_arrays",
           "run_map_landmarks"]

"""The commands ``render``, ``preview`` and ``report`` (the pictures of a run): their parameters and runners.

Their work is in :mod:`retarget_cli.see.preview` and :mod:`retarget_cli.see.report`;
the CLI builds them from these declarations.
"""

from __future__ import annotations

from ..config import Command, Flag, Param, output_flag
from ..errors import UsageError
from ..methods.render import Camera
from ..run.runfiles import locate_run
from .preview import write_preview, write_render
from .report import write_report

#: The camera of ``render``, ``preview`` and ``report`` (:class:`retarget_cli.methods.render.Camera`).
CAMERA_PARAMS = [
    Param("yaw", "setting", float, -20.0, "Camera turn about the mesh's vertical axis, in degrees."),
    Param("pitch", "setting", float, 10.0, "Camera tilt in degrees (positive looks down on the mesh)."),
    Param("fov", "setting", float, 30.0, "Vertical field of view in degrees; 0 for an orthographic view.",
          min=0, max=170, max_open=True),
    Param("distance", "setting", float, None, "Camera distance in bounding radii (default: the mesh fills the view).",
          min=1, min_open=True, nullable=True),
    Param("shading", "setting", str, "gouraud", "Interpolated (gouraud) or per-face (flat) lighting.",
          choices=("gouraud", "flat")),
]

#: ``render``.
RENDER_PARAMS = [
    Param("mesh", "input", str, help="An OBJ, or an OBJ sequence (a directory or a glob)."),
    Param("output", "output", str, help="Image (.png, .jpg) for one OBJ; video (.mp4, .avi) for a sequence."),
    Param("size", "setting", list, [512, 512], "Image size WxH, or N for N x N pixels."),
    Param("fps", "setting", float, 30.0, "Frame rate of a video output.", min=0, max=240, min_open=True),
    *CAMERA_PARAMS,
]

#: ``preview``.
PREVIEW_PARAMS = [
    Param("run_path", "input", str, help="A config YAML or a run's output directory."),
    Param("output", "output", str, "preview.mp4", "Video file."),
    Param("frames", "setting", str, None, "Source frames A:B (as curves.csv's frame column names them; B excluded), "
          "e.g. 100:220, or one frame; a negative value counts frames from the end.", nullable=True),
    Param("size", "setting", int, 360, "Height of each panel in pixels.", min=32, max=2160),
    Param("fps", "setting", float, None, "Frame rate (default: the take's).", min=0, max=240, min_open=True,
          nullable=True),
    Param("video", "input", str, None, "Source video (default: the one the run's config or track manifest names).",
          nullable=True),
    *CAMERA_PARAMS,
]

#: ``report``.
REPORT_PARAMS = [
    Param("run_path", "input", str, help="A config YAML or a run's output directory."),
    Param("output", "output", str, "report.html", "HTML file (self-contained: images embedded)."),
    Param("video", "input", str, None, "Source video (default: the one the run's config or track manifest names).",
          nullable=True),
    Param("worst", "setting", int, 6, "Worst frames listed and thumbnailed.", min=0, max=50),
    Param("truth", "input", str, None,
          "Ground truth of a synthetic take, for mesh error and jitter against it (retarget synth's truth.npz; "
          "default: the truth.npz beside the video, when there is one).", nullable=True),
    *CAMERA_PARAMS,
]


def _camera(values: dict) -> dict:
    """The camera settings of *values* (removed from it) as ``write_*``'s camera and shading keywords."""
    cam = Camera(**{k: values.pop(k) for k in ("yaw", "pitch", "fov", "distance")})
    return dict(camera=cam, shading=values.pop("shading"))


def _cli_render(values, out):
    kw = dict(values)
    return [write_render(kw.pop("mesh"), kw.pop("output"), **_camera(kw), **kw, progress=out.progress)]


def _cli_preview(values, out):
    kw = dict(values)
    run_files = locate_run(kw.pop("run_path"), video=kw.pop("video"))
    try:
        return [write_preview(run_files, kw.pop("output"), height=kw.pop("size"), **_camera(kw), **kw,
                              progress=out.progress)]
    except ValueError as exc:
        if str(exc).startswith("--frames"):
            raise UsageError(str(exc)) from None
        raise


def _cli_report(values, out):
    kw = dict(values)
    run_files = locate_run(kw.pop("run_path"), video=kw.pop("video"))
    return [write_report(run_files, kw.pop("output"), **_camera(kw), **kw, progress=out.progress)]


_CAMERA_FLAGS = tuple(p.name for p in CAMERA_PARAMS)

#: ``render``, ``preview`` and ``report`` (the CLI builds them: :mod:`retarget_cli.cli.commands`).
COMMANDS = [
    Command(
        "render",
        """Render an OBJ (to an image) or an OBJ sequence (a directory or glob, to a video).

    Uses the built-in software rasteriser (no GPU or display needed); the camera
    is framed on the first mesh and stays fixed.
    """,
        lambda: RENDER_PARAMS,
        (Flag("mesh", argument=True, metavar="MESH_OR_SEQUENCE"),
         output_flag(None, "Image (.png, .jpg) for one OBJ; video (.mp4, .avi) for a sequence."),
         Flag("size", value="size", value_args=(("square", True), ("example", "512x512")), default="512",
              metavar="WxH"),
         "fps", *_CAMERA_FLAGS),
        _cli_render,
    ),
    Command(
        "preview",
        """Side-by-side video of a run: tracked source | retargeted character | weights.

    RUN_DIR_OR_CONFIG is a config YAML (paths resolved as `retarget run` does) or
    a run's output directory with the default file names.
    """,
        lambda: PREVIEW_PARAMS,
        (Flag("run_path", argument=True, metavar="RUN_DIR_OR_CONFIG", path="existing"),
         output_flag("preview.mp4", "Video file, or an image (.png, .jpg) of the one frame --frames names.",
                     required=False),
         Flag("frames", metavar="A:B", show_default=False), "size", "fps", Flag("video", path="file"),
         *_CAMERA_FLAGS),
        _cli_preview,
    ),
    Command(
        "report",
        """One self-contained HTML page about a run: summary, tracking, keys, weights, residuals.

    On a synthetic take, also the mesh error and jitter against the truth.

    Needs matplotlib: pip install 'retarget[report]'.
    """,
        lambda: REPORT_PARAMS,
        (Flag("run_path", argument=True, metavar="RUN_DIR_OR_CONFIG", path="existing"),
         output_flag("report.html", "HTML file (self-contained: images embedded).", required=False),
         Flag("video", path="file"), "worst", Flag("truth", path="file"), *_CAMERA_FLAGS),
        _cli_report,
    ),
]

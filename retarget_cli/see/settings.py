"""Declared parameters of ``render``, ``preview`` and ``report`` (the pictures of a run).

Their work is in :mod:`retarget_cli.see.preview` and :mod:`retarget_cli.see.report`;
the CLI builds their options from these declarations.
"""

from __future__ import annotations

from ..config import Param

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
    Param("frames", "setting", str, None, "Frame range (Python slice), e.g. 0:120.", nullable=True),
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

#: ``synth`` (:func:`retarget_cli.synth.take.write_take`).
SYNTH_PARAMS = [
    Param("outdir", "output", str, help="Folder for the take."),
    Param("frames", "setting", int, 240, "Number of frames.", min=2, max=100000),
    Param("size", "setting", list, [320, 320], "Frame size WxH in pixels."),
    Param("seed", "setting", int, 0, "Random seed.", min=0),
]

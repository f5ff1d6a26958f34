"""Landmark tracking and head-motion separation.

:data:`TRACKERS` is the registry of ``track --method``: adding a tracker is one
new module (a function as :mod:`retarget_cli.methods.tracking.base` describes) and one
entry here; the method's choices, help and docs are made from it
(docs/howto-add-tracker.md).
"""

from .base import TrackerSpec

#: Tracking methods by name, in the order ``--method`` lists them.
TRACKERS: dict[str, TrackerSpec] = {
    "detect": TrackerSpec(
        "dlib's pretrained 68-point detector on every frame joined with optical flow; needs the extra detect",
        "retarget_cli.methods.tracking.detect:track_detect", settings=("downscale", "fuse"), gray=True, needs=("detector",),
        gaps=True, on_frame=True),
    "lk": TrackerSpec(
        "Lucas-Kanade, one or more annotated frames",
        "retarget_cli.methods.tracking.lk:track_lk",
        settings=("window", "levels", "fb_threshold", "anchor", "rigid_points", "downscale"), gray=True),
    "eigenpoints": TrackerSpec(
        "the paper's tracker, trained on the annotated frames; give 5 or more",
        "retarget_cli.methods.tracking.eigenpoints:track_eigenpoints", settings=("rigid_points",)),
    "markers": TrackerSpec(
        "painted dots on the landmarks", "retarget_cli.methods.tracking.markers:track_markers"),
    "facemark": TrackerSpec(
        "OpenCV Facemark LBF with --model, see train-tracker",
        "retarget_cli.methods.tracking.facemark:track_facemark", settings=("rigid_points",), needs=("model",)),
}


def method_choices() -> tuple[str, ...]:
    """``auto`` and every registered method (``auto``: detect where its extra is installed, else lk)."""
    return ("auto", *TRACKERS)


def method_help() -> str:
    """The help of ``track.method``, made from :data:`TRACKERS`."""
    return ("Tracker: " + " or ".join(f"{name} ({spec.help})" for name, spec in TRACKERS.items())
            + "; auto: detect where the extra is installed, else lk.")


def tracker_params(known=()) -> list:
    """The settings registered trackers declare (:attr:`TrackerSpec.params`) that are not among *known* names."""
    out, seen = [], set(known)
    for spec in TRACKERS.values():
        for p in spec.params:
            if p.name not in seen:
                seen.add(p.name)
                out.append(p)
    return out

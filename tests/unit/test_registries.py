"""The two extension points: a tracker and an export registered from outside, touching no other file."""

import numpy as np
import pytest

from retarget_cli.config import Param
from retarget_cli.errors import ParameterError
from retarget_cli.io.exports import EXPORTS, Exporter, format_choices
from retarget_cli.io.landmarks import load_landmarks
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.stagefiles import save_weights, write_targets
from retarget_cli.methods.tracking import TRACKERS, TrackerSpec, method_choices, method_help
from retarget_cli.run.pipeline import STAGES
from retarget_cli.stages import run_apply, run_track


def _still(frames, annotations, *, progress, downscale, still_confidence):
    """A tracker that holds the first annotation in every frame, at a confidence of its own setting."""
    P = annotations[0]
    pts = []
    for _ in frames:
        pts.append(P)
        progress(len(pts))
    assert downscale == 1.0
    return np.stack(pts), np.full((len(pts), len(P)), still_confidence)


STILL = TrackerSpec("holds the first annotation", _still, settings=("downscale", "still_confidence"),
                    params=(Param("still_confidence", "setting", float, 0.5, "Confidence of every point.",
                                  min=0, max=1),))


def test_a_registered_tracker_is_a_method_everywhere(small_take, tmp_path, monkeypatch):
    monkeypatch.setitem(TRACKERS, "still", STILL)
    assert "still" in method_choices() and "still (holds the first annotation)" in method_help()
    # the stage's declarations (YAML validation, CLI choices, docs) follow the registry, its own setting too
    assert STAGES["track"].param("method").check("still", "config.yaml: track.method") == "still"
    assert STAGES["track"].param("still_confidence").default == 0.5
    out = tmp_path / "lm.npz"
    written = run_track(video=small_take / "face.mp4", init=small_take / "face_00000.pts", output=out,
                        method="still", filter="none")
    assert written == [out]
    lm = load_landmarks(out)
    assert lm.meta["tracker"] == "still" and lm.n_frames == 60
    first = lm.points[0]
    assert np.allclose(lm.points, first[None]) and np.allclose(lm.confidence, 0.5)
    run_track(video=small_take / "face.mp4", init=small_take / "face_00000.pts", output=out, method="still",
              filter="none", still_confidence=0.25)
    assert np.allclose(load_landmarks(out).confidence, 0.25)
    assert load_landmarks(out).meta["parameters"]["still_confidence"] == 0.25
    with pytest.raises(ParameterError, match="still_confidence"):
        run_track(video=small_take / "face.mp4", init=small_take / "face_00000.pts", output=out, method="still",
                  still_confidence=2.0)
    with pytest.raises(ParameterError, match="unexpected setting 'nonsense'"):
        run_track(video=small_take / "face.mp4", init=small_take / "face_00000.pts", output=out, nonsense=1)


class _NpyExport(Exporter):
    """Every frame (head motion applied) in one .npy file."""

    help = "frames.npy"
    files = ("frames.npy",)
    streams = True

    def __init__(self, ctx):
        super().__init__(ctx)
        self.frames = np.zeros((ctx.n_frames, ctx.n_vertices, 3))

    def add(self, start, frames):
        self.frames[start:start + len(frames)] = frames

    def finish(self):
        path = self.ctx.out / self.files[0]
        np.save(path, self.frames)
        return [path]


def test_a_registered_export_is_a_format(tmp_path, monkeypatch):
    monkeypatch.setitem(EXPORTS, "npy", _NpyExport)
    assert "npy" in format_choices()
    assert STAGES["apply"].param("formats").check(["obj", "npy"], "config.yaml: apply.formats") == ["obj", "npy"]
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], float)
    t = tmp_path / "t"
    t.mkdir()
    (t / "neutral.obj").write_bytes(format_obj(V, np.array([[0, 1, 3, 2]])))
    key = V + [0, 0, 1.0]
    (t / "k1.obj").write_bytes(read_obj(t / "neutral.obj").to_bytes(key))
    write_targets(t / "targets.yaml", {"face": {"keys": {0: "neutral.obj", 3: "k1.obj"}}}, neutral="neutral.obj")
    W = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])
    save_weights(tmp_path / "weights.npz", {"face": (W, np.array([0, 3]), np.zeros(3))}, {"fps": 24.0})
    out = tmp_path / "frames"
    written = run_apply(weights=tmp_path / "weights.npz", targets=t / "targets.yaml", output=out,
                        formats=["obj", "npy"])
    assert out / "frames.npy" in written and out / "frame_00002.obj" in written
    frames = np.load(out / "frames.npy")
    assert np.allclose(frames, W[:, :1, None] * V + W[:, 1:, None] * key)
    assert np.allclose(read_obj(out / "frame_00001.obj").vertices, frames[1], atol=1e-5)

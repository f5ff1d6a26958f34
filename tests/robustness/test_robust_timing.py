"""Issue #34 as a user meets it: image sequences (with gaps) through `run`, source frame numbers and times in every
output, inputs replaced while a stage runs, implausible frame rates, and the one-line errors of item 7."""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.annotations import write_pts
from retarget_cli.io.editfiles import read_animation


def _cli(*args):
    res = CliRunner().invoke(main, [*map(str, args)])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res


def _one_error(res) -> str:
    """The single error line of a failed command (and nothing else on stderr but warnings)."""
    assert res.exit_code != 0, res.output
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and "Traceback" not in res.output, res.stderr
    return errors[0]


def _frames_of(video: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            return out
        out.append(f)


def _config(take: Path, name: str, edit) -> Path:
    cfg = yaml.safe_load((take / "config.yaml").read_text())
    edit(cfg)
    path = take / name
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def _auto_pose(cfg: dict) -> None:
    """The rig posed by auto_pose (curves, Live Link, glTF) instead of the synthetic artist."""
    cfg.pop("pose")
    apply = cfg.pop("apply")
    cfg["auto_pose"] = {"rig": "rig.yaml"}
    cfg["apply"] = {**apply, "formats": ["obj", "csv", "curves", "livelink", "glb", "usd"]}


# --------------------------------------------------------------------------- image sequences through run


@pytest.mark.parametrize("pattern", ["seq/img_%05d.png", "seq/*.png"])
def test_image_sequence_with_and_without_a_gap_runs_through_every_stage(take, pattern):
    frames = _frames_of(take / "face.mp4")
    (take / "seq").mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(take / "seq" / f"img_{i:05d}.png"), f)

    def seq(out):
        def edit(c):
            c["output_dir"] = out
            c["track"]["video"] = pattern
            c["apply"]["formats"] = ["obj", "csv"]
            c["select"]["contact_sheet"] = "keys.png"  # the key frames cut from the sequence
        return edit

    full = _cli("run", _config(take, "seq.yaml", seq("full")))
    assert full.exit_code == 0, full.output
    for line in ("track: ran", "select: ran", "decompose: ran", "pose: ran", "apply: ran"):
        assert line in full.stderr
    assert "missing" not in full.stderr
    lm = np.load(take / "full/landmarks.npz")
    np.testing.assert_array_equal(lm["frames"], np.arange(len(frames)))

    gap = 11
    (take / "seq" / f"img_{gap:05d}.png").unlink()  # a frame lost from the sequence
    res = _cli("run", _config(take, "gap.yaml", seq("gap")))
    assert res.exit_code == 0, res.output
    warned = [ln for ln in res.stderr.splitlines() if "missing from the numbering" in ln]
    assert len(warned) == 1 and f"frame {gap}," in warned[0], res.stderr
    g = np.load(take / "gap/landmarks.npz")
    T = len(frames)
    np.testing.assert_array_equal(g["frames"], np.arange(T))  # kept as a gap: later frames keep their numbers
    np.testing.assert_allclose(g["times"], np.arange(T) / 30.0)
    assert np.all(g["confidence"][gap] == 0) and np.all(g["confidence"][gap + 1] > 0)
    # every later frame lines up with the sequence tracked without the gap (not one frame early)
    later = np.abs(g["points_raw"][gap + 2:] - lm["points_raw"][gap + 2:]).mean()
    one_early = np.abs(g["points_raw"][gap + 2:-1] - lm["points_raw"][gap + 3:]).mean()
    assert later < 0.25 * one_early, (later, one_early)
    keys = json.loads((take / "gap/keys.json").read_text())
    assert all(gap not in r["frames"] for r in keys["regions"].values())  # a lost frame is never a key
    assert cv2.imread(str(take / "gap/keys.png")) is not None
    w = np.load(take / "gap/weights.npz")
    assert any(w[k][gap] for k in w.files if k.endswith("_lost"))
    rows = (take / "gap/frames/weights.csv").read_text().splitlines()
    assert len(rows) == T + 1 and rows[gap + 1].startswith(f"{gap},{gap / 30:.6f},")


# --------------------------------------------------------------------------- timing of every output


def _glb_times(path: Path) -> tuple[float, float]:
    data = path.read_bytes()
    n = struct.unpack("<I", data[12:16])[0]
    doc = json.loads(data[20:20 + n])
    acc = doc["accessors"][doc["animations"][0]["samplers"][0]["input"]]
    return acc["min"][0], acc["max"][0]


def test_curves_of_a_start_step_run_line_up_with_landmarks_and_video(take):
    pytest.importorskip("pxr", reason="the usd export needs the extra usd (usd-core)")
    fps = cv2.VideoCapture(str(take / "face.mp4")).get(cv2.CAP_PROP_FPS)
    truth = np.load(take / "truth_landmarks.npz")
    write_pts(take / "face_00006.pts", truth["points"][6])

    def edit(c):
        c["output_dir"] = "ss"
        c["track"].update(init="face_00006.pts", start=6, step=2)
        c["select"]["k"] = 4
        _auto_pose(c)

    res = _cli("run", _config(take, "ss.yaml", edit))
    assert res.exit_code == 0, res.output
    out = take / "ss"
    lm = np.load(out / "landmarks.npz")
    expected = np.arange(6, 24, 2)
    np.testing.assert_array_equal(lm["frames"], expected)
    np.testing.assert_allclose(lm["times"], expected / fps)  # the video's timestamps
    names, C, frames, times = read_animation(out / "frames/curves.csv")
    np.testing.assert_array_equal(frames, lm["frames"])
    np.testing.assert_allclose(times, lm["times"], atol=1e-6)
    npz = np.load(out / "frames/curves.npz")
    np.testing.assert_array_equal(npz["frames"], lm["frames"])
    np.testing.assert_allclose(npz["times"], lm["times"])
    w = np.load(out / "weights.npz")
    np.testing.assert_array_equal(w["frame"], lm["frames"])
    np.testing.assert_allclose(w["time"], lm["times"])
    assert (out / "frames/weights.csv").read_text().splitlines()[1].startswith(f"6,{6 / fps:.6f},")
    live = (out / "frames/livelink.csv").read_text().splitlines()
    assert live[1].startswith("00:00:00:06.000,") and live[2].startswith("00:00:00:08.000,")
    lo, hi = _glb_times(out / "frames/animation.glb")
    assert lo == pytest.approx(6 / fps, abs=1e-6) and hi == pytest.approx(22 / fps, abs=1e-6)
    from pxr import Usd

    stage = Usd.Stage.Open(str(out / "frames/animation.usd"))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetTimeCodesPerSecond()) == (6, 22, fps)


def test_implausible_frame_rate_is_refused_and_track_fps_sets_it(take):
    frames = _frames_of(take / "face.mp4")
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(take / "remux.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 2344.0, (w, h))
    for f in frames:
        writer.write(f)
    writer.release()
    args = ["track", "--method", "lk", take / "remux.mp4", "--init", take / "face_00000.pts"]
    line = _one_error(_cli(*args, "-o", take / "a.npz"))
    assert "remux.mp4" in line and "2344 fps" in line and "track.fps" in line
    assert not (take / "a.npz").exists()
    res = _cli(*args, "-o", take / "b.npz", "--fps", 30)
    assert res.exit_code == 0, res.output
    lm = np.load(take / "b.npz")
    assert lm["fps"] == 30 and lm["times"][-1] == pytest.approx((len(frames) - 1) / 30)


def test_missing_frame_rate_is_replaced_with_a_warning(caplog):
    from retarget_cli.io.frames import plausible_fps

    with caplog.at_level(logging.WARNING, logger="retarget_cli.io.frames"):
        assert plausible_fps(float("nan"), "clip.mp4") == 30.0
        assert plausible_fps(0.0, "clip.mp4") == 30.0
    assert len(caplog.records) == 2 and "clip.mp4: no frame rate" in caplog.records[0].getMessage()
    assert plausible_fps(float("nan"), "clip.mp4", given=24) == 24


# --------------------------------------------------------------------------- inputs that change


def test_input_replaced_while_a_stage_runs_fails_it_and_the_rerun_reruns(take, monkeypatch):
    import retarget_cli.stages.track as track

    init = take / "face_00000.pts"
    original = init.read_bytes()
    read = track.read_annotations

    def read_then_replace(*a, **k):  # the user saves another annotation while track is running
        got = read(*a, **k)
        lines = original.decode().splitlines()
        moved = [" ".join(f"{float(v) + 0.5:.3f}" for v in ln.split()) for ln in lines[3:-1]]
        init.write_text("\n".join(lines[:3] + moved + lines[-1:]) + "\n")  # (by the user, not through retarget)
        return got

    monkeypatch.setattr(track, "read_annotations", read_then_replace)
    res = _cli("run", take / "config.yaml", "--force", "--until", "track")
    line = _one_error(res)
    assert str(init) in line and "changed while stage 'track' ran" in line
    monkeypatch.undo()
    again = _cli("run", take / "config.yaml", "--until", "track")
    assert again.exit_code == 0 and "track: ran" in again.stderr, again.output
    third = _cli("run", take / "config.yaml", "--until", "track")
    assert third.exit_code == 0 and "track: skipped" in third.stderr, third.output
    man = json.loads((take / "out/.retarget/track.json").read_text())
    assert man["inputs"]["face_00000.pts"]["sha256"] == hashlib.sha256(init.read_bytes()).hexdigest()
    assert init.read_bytes() != original


# --------------------------------------------------------------------------- item 7: errors that name their place


def test_obj_vertex_at_1e308_names_file_and_vertex(take):
    smile = take / "target/shapes/smile.obj"
    lines = smile.read_text().splitlines()
    i = [k for k, ln in enumerate(lines) if ln.startswith("v ")][5]
    lines[i] = "v 1e308 0 0"
    smile.write_text("\n".join(lines) + "\n")
    line = _one_error(_cli("run", take / "config.yaml", "--no-cache"))
    assert "smile.obj" in line and "vertex 5" in line and "1e+308" in line and "internal error" not in line


def test_full_disk_names_the_file_and_the_stage(take, monkeypatch):
    import retarget_cli.io.atomic as atomic

    real = os.fdopen

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fdopen", lambda fd, *a, **k: Full(real(fd, *a, **k)))
    line = _one_error(_cli("run", take / "config.yaml", "--force", "--from", "decompose", "--until", "decompose"))
    monkeypatch.undo()
    assert "stage 'decompose'" in line and "weights.npz" in line and "No space left on device" in line
    assert not list((take / "out").glob(".*.part"))


def test_landmarks_list_holding_minus_one_names_the_entry(take):
    rig = take / "rig.yaml"
    ids = list(range(100, 168))
    ids[50] = -1
    rig.write_text(rig.read_text() + f"landmarks: {ids}\n")
    line = _one_error(_cli("auto-pose", take / "out/keys.json", take / "out/landmarks.npz", rig, "-o", take / "ap"))
    assert "rig.yaml: landmarks[50] = '-1'" in line


def _curves_file(take: Path, rows: list[str]) -> Path:
    names = yaml.safe_load((take / "rig.yaml").read_text())["shapes"]
    path = take / "curves.csv"
    path.write_text("frame," + ",".join(names) + "\n" + "".join(r + "\n" for r in rows))
    return path


def test_edit_pin_at_nan_names_the_edit(take):
    n = len(yaml.safe_load((take / "rig.yaml").read_text())["shapes"])
    curves = _curves_file(take, [f"{t}," + ",".join(["0.1"] * n) for t in range(6)])
    edits = take / "edits.yaml"
    edits.write_text("edits:\n  - pin:\n      frames: [2, 4]\n      constraints:\n"
                     "        - {vertex: 10, position: [.nan, 0, 0]}\n")
    line = _one_error(_cli("edit", curves, edits, "--rig", take / "rig.yaml", "-o", take / "e.csv"))
    assert "edits[0].pin.constraints[0].position" in line and "nan" in line


def test_short_csv_row_gives_the_line_number(take):
    n = len(yaml.safe_load((take / "rig.yaml").read_text())["shapes"])
    rows = [f"{t}," + ",".join(["0.1"] * n) for t in range(6)]
    rows[2] = rows[2].rsplit(",", 1)[0]  # line 4 of the file
    (take / "edits.yaml").write_text("edits: []\n")
    line = _one_error(_cli("edit", _curves_file(take, rows), take / "edits.yaml", "--rig", take / "rig.yaml",
                           "-o", take / "e.csv"))
    assert "curves.csv:4:" in line and f"{n} values, expected {n + 1}" in line


def test_slider_name_with_a_comma_is_quoted_and_read_back(take):
    rig = take / "rig.yaml"
    rig.write_text(rig.read_text().replace("  smile: ", '  "smile,wide": '))
    res = _cli("auto-pose", take / "out/keys.json", take / "out/landmarks.npz", rig, "-o", take / "ap")
    assert res.exit_code == 0, res.output
    names, *_ = read_animation(take / "ap/sliders.csv")
    assert "smile,wide" in names and len(names) == len(yaml.safe_load(rig.read_text())["shapes"])
    res = _cli("apply", take / "out/weights.npz", take / "ap/targets.yaml", "-o", take / "apf", "--format", "curves")
    assert res.exit_code == 0, res.output
    assert "smile,wide" in read_animation(take / "apf/curves.csv")[0]


def test_preview_of_a_run_whose_config_lives_elsewhere(take, tmp_path):
    elsewhere = tmp_path / "elsewhere"

    def edit(c):
        c["output_dir"] = str(elsewhere / "out")

    assert _cli("run", _config(take, "away.yaml", edit)).exit_code == 0
    res = _cli("preview", elsewhere / "out", "-o", tmp_path / "p.mp4", "--frames", "0:2")
    assert res.exit_code == 0 and "not found" not in res.stderr, res.output
    left = cv2.VideoCapture(str(tmp_path / "p.mp4")).read()[1][40:-40, :20]
    assert left.std() > 5  # the source video, not a flat grey panel
    shutil.move(elsewhere / "out", tmp_path / "moved")
    shutil.move(take / "face.mp4", take / "face_moved.mp4")
    res = _cli("preview", tmp_path / "moved", "-o", tmp_path / "q.mp4", "--frames", "0:2")
    assert res.exit_code == 0, res.output
    warned = [ln for ln in res.stderr.splitlines() if "was not found" in ln]
    assert len(warned) == 1 and "face.mp4" in warned[0] and "--video" in warned[0]
    grey = cv2.VideoCapture(str(tmp_path / "q.mp4")).read()[1][40:-40, :20]
    assert grey.std() < 5 < left.std()  # said, and the measure above tells a blank panel from the video


def test_annotate_hint_names_its_own_options(tmp_path):
    from retarget_cli.methods.tracking.detect import detector_installed

    if not detector_installed():
        pytest.skip("needs the extra detect (the pretrained detector)")
    seq = tmp_path / "blank"
    seq.mkdir()
    for i in range(2):
        cv2.imwrite(str(seq / f"b_{i:03d}.png"), np.full((120, 120, 3), 90, np.uint8))
    line = _one_error(_cli("annotate", seq / "b_%03d.png", "--frames", "1", "-o", tmp_path / "ann"))
    assert "frame 1: no face found" in line and "--frames" in line and "--init" not in line


# --------------------------------------------------------------------------- every output names source frames


def _video_frames(path: Path) -> int:
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    return n


@pytest.fixture(scope="module")
def from_100(tmp_path_factory):
    """A 140-frame synthetic take run with ``track.start: 100, end: 140, step: 2`` (20 frames), the rig posed by
    auto_pose, every export with frames written."""
    from retarget_cli.synth.take import write_take

    d = tmp_path_factory.mktemp("from100") / "take"
    write_take(d, n_frames=140, size=(96, 96), seed=0)
    write_pts(d / "face_00100.pts", np.load(d / "truth_landmarks.npz")["points"][100])

    def edit(c):
        c["track"].update(init="face_00100.pts", start=100, end=140, step=2)
        c["select"]["k"] = 4
        _auto_pose(c)
        c["apply"]["formats"] = ["obj", "csv", "exr", "curves", "livelink"]

    res = _cli("-q", "run", _config(d, "from100.yaml", edit))
    assert res.exit_code == 0, res.output
    return d


def test_every_output_with_frames_names_the_source_frames(from_100):
    """Issue #34: OBJ frame files, the EXR's rows, keys.json, targets.yaml, weights and curves of a
    ``start: 100, step: 2`` run all name source frames 100, 102, … and line up with landmarks.npz."""
    from retarget_cli.io.exr import read_vat, read_vat_frames
    from retarget_cli.io.obj import read_obj

    out = from_100 / "out"
    lm = np.load(out / "landmarks.npz")
    source = np.arange(100, 140, 2)
    np.testing.assert_array_equal(lm["frames"], source)
    fps = cv2.VideoCapture(str(from_100 / "face.mp4")).get(cv2.CAP_PROP_FPS)  # the video's own rate
    np.testing.assert_allclose(lm["times"], source / fps)

    # keys.json names key frames by source frame, and keeps their rows
    keys = json.loads((out / "keys.json").read_text())
    for name, reg in keys["regions"].items():
        assert set(reg["frames"]) <= set(source.tolist()), (name, reg["frames"])
        np.testing.assert_array_equal(lm["frames"][reg["rows"]], reg["frames"])
    neutral = keys["neutral"]
    assert neutral["frame"] == int(lm["frames"][neutral["row"]]) and neutral["frame"] >= 100
    # ... and so do the weights' key columns, targets.yaml's keys and the key OBJs
    w = np.load(out / "weights.npz")
    targets = yaml.safe_load((out / "targets" / "targets.yaml").read_text())
    for name, reg in keys["regions"].items():
        np.testing.assert_array_equal(w[f"{name}_frames"], reg["frames"])
        assert sorted(targets["regions"][name]["keys"]) == sorted(reg["frames"])
        for f in reg["frames"]:
            assert (out / "targets" / name / f"key_{f:05d}.obj").is_file()
    assert (out / "frames/weights.csv").read_text().splitlines()[0].split(",")[2].split(":")[1] in \
        {str(f) for r in keys["regions"].values() for f in r["frames"]}

    # OBJ frames are named by source frame, one per row of curves.csv (its frame column)
    objs = sorted((out / "frames").glob("frame_*.obj"))
    assert [p.name for p in objs] == [f"frame_{f:05d}.obj" for f in source]
    names, C, frames, times = read_animation(out / "frames/curves.csv")
    np.testing.assert_array_equal(frames, source)
    np.testing.assert_allclose(times, lm["times"], atol=1e-6)
    sliders, S, sframes, _ = read_animation(out / "targets" / "curves.csv")  # auto-pose's every-frame curves
    np.testing.assert_array_equal(sframes, source)

    # the EXR's rows carry the same numbers (header and sidecar), row t being frame_<frames[t]>.obj
    np.testing.assert_array_equal(read_vat_frames(out / "frames/animation.exr"), source)
    side = json.loads((out / "frames/animation.json").read_text())
    assert side["source_frames"] == source.tolist() and side["source_fps"] == pytest.approx(fps)
    np.testing.assert_allclose(side["times"], lm["times"], atol=1e-6)
    vat = read_vat(out / "frames/animation.exr")
    first = read_obj(out / "frames/frame_00100.obj").vertices
    for t in (3, 11, 19):
        moved = read_obj(out / f"frames/frame_{source[t]:05d}.obj").vertices - first
        np.testing.assert_allclose(vat[t] - vat[0], moved, atol=1e-4)

    # frame_<f>.obj is the rig posed at curves.csv's row of frame f (apply drives the rig; no head motion)
    from retarget_cli.io.rig import load_rig

    rig = load_rig(from_100 / "rig.yaml", cache_dir=None)
    npz = np.load(out / "frames/curves.npz")
    np.testing.assert_array_equal(npz["frames"], source)
    cols = [rig.index[n] for n in npz["names"]]
    for t in (0, 7, 19):
        w = np.zeros(rig.n_sliders)
        w[cols] = npz["curves"][t]
        np.testing.assert_allclose(read_obj(out / f"frames/frame_{source[t]:05d}.obj").vertices, rig.evaluate(w),
                                   atol=2e-6)


def test_pose_keys_poses_a_key_at_its_source_frame(from_100, tmp_path):
    """The synthetic artist (``pose-keys --poses truth.npz``, the video's every frame) poses key frame f at the
    truth's frame f, not at its row of a take tracked from frame 100."""
    from retarget_cli.io.obj import read_obj
    from retarget_cli.io.rig import load_rig

    out = from_100 / "out"
    masks = [a for r in ("brows-eyes", "mouth") for a in ("--mask", f"{r}={from_100}/target/regions/{r}.txt")]
    res = _cli("pose-keys", out / "keys.json", from_100 / "rig.yaml", "--poses", from_100 / "truth.npz", *masks,
               "-o", tmp_path / "keys")
    assert res.exit_code == 0, res.output
    truth = np.load(from_100 / "truth.npz")
    rig = load_rig(from_100 / "rig.yaml", cache_dir=None)
    cols = [rig.index[str(n)] for n in truth["names"]]
    keys = json.loads((out / "keys.json").read_text())
    name, reg = next(iter(keys["regions"].items()))
    for f, row in zip(reg["frames"], reg["rows"]):
        w = np.zeros(rig.n_sliders)
        w[cols] = truth["curves"][f]
        got = read_obj(tmp_path / "keys" / name / f"key_{f:05d}.obj").vertices
        np.testing.assert_allclose(got, rig.evaluate(w), atol=2e-6)
        if not np.allclose(truth["curves"][f], truth["curves"][row]):
            w[cols] = truth["curves"][row]
            assert not np.allclose(got, rig.evaluate(w), atol=2e-6)


def test_preview_frames_are_source_frame_numbers(from_100, tmp_path):
    """``preview --frames`` takes the numbers curves.csv's frame column shows; a frame not in the take is one
    line naming the take's frames."""
    from retarget_cli.run.runfiles import locate_run
    from retarget_cli.see.preview import RunData, preview_frames

    cfg = from_100 / "from100.yaml"
    res = _cli("preview", cfg, "-o", tmp_path / "a.mp4", "--frames", "104:110", "--size", "96")
    assert res.exit_code == 0, res.output
    assert _video_frames(tmp_path / "a.mp4") == 3  # frames 104, 106, 108
    res = _cli("preview", cfg, "-o", tmp_path / "b.mp4", "--frames", "138", "--size", "96")
    assert res.exit_code == 0, res.output
    assert _video_frames(tmp_path / "b.mp4") == 1
    for spec, what in (("101", "frame 101 is not a frame of the take"), ("4", "frame 4 is not a frame of the take"),
                       ("0:100", "selects no frame")):
        res = _cli("preview", cfg, "-o", tmp_path / "c.mp4", "--frames", spec)
        assert res.exit_code == 2, res.output
        lines = [ln for ln in res.output.splitlines() if ln.startswith("Error")]  # (a usage error: click's form)
        assert len(lines) == 1 and what in lines[0] and "source frames 100-138, every 2nd" in lines[0], res.output
        assert "Traceback" not in res.output
    assert not (tmp_path / "c.mp4").exists()

    # the source panel of frame 120 is the video's frame 120 (not its row 10, nor frame 10)
    data = RunData(locate_run(cfg))
    row = data.row_of(120)
    assert row == 10 and data.source_time(row)[0] == 120
    panel = next(preview_frames(data, range(row, row + 1), height=96))[:96, :96].astype(int)
    video = _frames_of(from_100 / "face.mp4")
    yy, xx = np.mgrid[0:96, 0:96]  # away from the drawn landmarks and the two text lines
    pts = data.lm.points[row]
    far = (np.min(np.hypot(xx[..., None] - pts[:, 0], yy[..., None] - pts[:, 1]), -1) > 4) & (yy > 24) & (yy < 74)
    diff = {f: np.abs(panel[far] - video[f][far].astype(int)).mean() for f in (120, 10, 110)}
    assert diff[120] < 1.5 and diff[120] < 0.5 * min(diff[10], diff[110]), diff


def test_report_names_source_frames(from_100, tmp_path):
    """The report's key table, rest pose and worst frames name source frames 100, 102, … (and their times)."""
    import re

    pytest.importorskip("matplotlib", reason="the report needs the extra report (matplotlib)")
    res = _cli("report", from_100 / "from100.yaml", "-o", tmp_path / "r.html", "--worst", "3")
    assert res.exit_code == 0, res.output
    page = (tmp_path / "r.html").read_text()
    keys = json.loads((from_100 / "out/keys.json").read_text())
    for reg in keys["regions"].values():
        assert ", ".join(str(f) for f in reg["frames"]) in page
    assert f"Neutral frame <b>{keys['neutral']['frame']}</b>" in page
    listed = [int(f) for f in re.findall(r'alt="source frame (\d+)"', page)]
    assert listed and set(listed) <= set(range(100, 140, 2)), listed

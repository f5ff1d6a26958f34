"""`retarget train-tracker` -> `retarget track --method facemark --model`, and their input errors."""

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.annotations import write_csv_landmarks, write_pts
from retarget_cli.io.atomic import load_npz

ANNOTATED = [0, 12, 24, 36, 48]


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def trained(small_take_template, tmp_path_factory):
    """A model trained by the CLI from 5 annotated frames (4 .pts files and a CSV), small cascade."""
    d = tmp_path_factory.mktemp("train")
    truth = load_npz(small_take_template / "truth_landmarks.npz")["points"]
    for f in ANNOTATED[:4]:
        write_pts(d / f"face_{f:05d}.pts", truth[f])
    write_csv_landmarks(d / "more.csv", truth[ANNOTATED[4:]], frames=ANNOTATED[4:])
    model = d / "actor.yaml"
    r = run("train-tracker", small_take_template / "face.mp4", *sorted(d.glob("face_*.pts")), d / "more.csv",
            "-o", model, "--stages", 3, "--trees", 2)
    assert r.exit_code == 0, r.output
    assert r.output.strip().splitlines()[-1] == str(model)
    return d, model, truth


def test_train_tracker_then_track_facemark(small_take_template, trained, tmp_path):
    d, model, truth = trained
    out = tmp_path / "lm.npz"
    r = run("track", small_take_template / "face.mp4", "--init", d / "face_00000.pts", "--method", "facemark",
            "--model", model, "-o", out)
    assert r.exit_code == 0, r.output
    lm = load_npz(out)
    err = np.linalg.norm(lm["points"] - truth, axis=2).mean()
    assert err < 0.8, err
    assert '"tracker": "facemark"' in str(lm["meta"]) and '"model": "actor.yaml"' in str(lm["meta"])
    assert lm["head"].shape == (60, 2, 3) and np.isfinite(lm["stabilized"]).all()


def test_facemark_needs_an_existing_model_for_the_same_point_count(small_take_template, trained, tmp_path):
    d, model, truth = trained
    video, init = small_take_template / "face.mp4", d / "face_00000.pts"
    r = run("track", video, "--init", init, "--method", "facemark", "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "method facemark needs a model file" in r.output
    r = run("track", video, "--init", init, "--method", "facemark", "--model", tmp_path / "none.yaml",
            "-o", tmp_path / "a.npz")
    assert r.exit_code == 1 and "none.yaml: Facemark model file not found" in r.output
    few = tmp_path / "few_00000.pts"
    write_pts(few, truth[0, :20])
    r = run("track", video, "--init", few, "--method", "facemark", "--model", model, "-o", tmp_path / "a.npz")
    assert r.exit_code == 1
    assert "actor.yaml: the Facemark model was trained for 68 points but" in r.output and "few_00000.pts has 20" \
        in r.output


def test_train_tracker_input_errors(small_take_template, trained, tmp_path):
    d, model, truth = trained
    video = small_take_template / "face.mp4"
    write_pts(tmp_path / "a_00003.pts", truth[3, :30])
    r = run("train-tracker", video, d / "face_00000.pts", tmp_path / "a_00003.pts", "-o", tmp_path / "m.yaml")
    assert r.exit_code == 1
    assert "a_00003.pts: frame 3 has 30 points but" in r.output and "face_00000.pts (frame 0) has 68" in r.output
    write_pts(tmp_path / "b_00500.pts", truth[5])
    r = run("train-tracker", video, d / "face_00000.pts", tmp_path / "b_00500.pts", "-o", tmp_path / "m.yaml")
    assert r.exit_code == 1 and "b_00500.pts: frame 500 is past the last frame" in r.output
    r = run("train-tracker", video, "-o", tmp_path / "m.yaml")
    assert r.exit_code == 2  # no annotation: usage error
    assert not (tmp_path / "m.yaml").exists()

"""`retarget select` with methods, regions, evaluation, plot and contact sheet (issue 4)."""

import json

import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.cli.types import RegionSpec


def test_region_specs_parse_presets_ranges_and_per_region_k():
    specs = ["mouth", "brows-eyes:6", "lips=48-50,60:4", "face=all"]
    assert dict(RegionSpec().convert(s, None, None) for s in specs) == {
        "mouth": None, "brows-eyes": {"points": None, "k": 6}, "lips": {"points": [48, 49, 50, 60], "k": 4},
        "face": "all"}


def test_select_evaluate_plot_contact_sheet(small_take, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "o"
    args = ["select", str(small_take / "truth_landmarks.npz"), "-o", str(out / "keys.json"), "-k", "5",
            "--method", "greedy", "--region", "brows-eyes", "--region", "mouth:6",
            "--evaluate", str(out / "curve.csv"), "--plot", str(out / "curve.png"), "--evaluate-k", "8",
            "--contact-sheet", str(out / "sheet.png"), "--video", str(small_take / "face.mp4")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output + r.stderr
    keys = json.loads((out / "keys.json").read_text())["regions"]
    assert len(keys["brows-eyes"]["frames"]) == 5 and len(keys["mouth"]["frames"]) == 6
    assert keys["mouth"]["points"] == list(range(3, 14)) + list(range(48, 68))
    summary = json.loads((out / "curve.json").read_text())["regions"]
    assert summary["mouth"]["k"] == 6 and summary["mouth"]["winner"] in summary["mouth"]["errors"]
    assert summary["mouth"]["selected_error"] == pytest.approx(summary["mouth"]["errors"]["greedy"], abs=1e-6)
    csv = (out / "curve.csv").read_text().splitlines()
    assert csv[0] == "region,curve,method,k,error,frames" and any(",kmeans-3pc," in line for line in csv)
    png = (out / "curve.png").read_bytes()
    sheet = (out / "sheet.png").read_bytes()
    assert png[:4] == b"\x89PNG" and sheet[:4] == b"\x89PNG"
    # Deterministic: a second run writes the same bytes.
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0
    assert (out / "curve.png").read_bytes() == png and (out / "sheet.png").read_bytes() == sheet


def test_contact_sheet_needs_the_video_and_presets_need_68_points(small_take, tmp_path):
    lm = str(small_take / "truth_landmarks.npz")
    r = CliRunner().invoke(main, ["select", lm, "-o", str(tmp_path / "k.json"), "--contact-sheet", str(tmp_path / "s.png")])
    assert r.exit_code == 1 and "needs the video" in r.stderr
    r = CliRunner().invoke(main, ["select", lm, "-o", str(tmp_path / "k.json"), "--region", "nose"])
    assert r.exit_code == 1 and "'nose' needs 'points'" in r.stderr


def test_frames_with_lost_landmarks_are_left_out_of_selection(small_take, tmp_path):
    import numpy as np

    from retarget_cli.errors import InputError
    from retarget_cli.io.atomic import load_npz, savez
    from retarget_cli.io.stagefiles import read_keys
    from retarget_cli.stages import run_select

    points = load_npz(small_take / "truth_landmarks.npz")["points"].copy()
    points[[7, 30], 50] = np.nan  # a mouth landmark lost in two frames
    savez(tmp_path / "lost.npz", {"points": points})
    run_select(landmarks=tmp_path / "lost.npz", output=tmp_path / "keys.json", method="greedy", k=6, neutral_frame=0)
    frames = read_keys(tmp_path / "keys.json").regions["face"]["frames"]
    assert len(frames) == 6 and 7 not in frames and 30 not in frames and 0 in frames
    points[0, 50] = np.nan
    savez(tmp_path / "lost0.npz", {"points": points})
    with pytest.raises(InputError, match="neutral frame 0 has lost"):
        run_select(landmarks=tmp_path / "lost0.npz", output=tmp_path / "keys.json", k=6, neutral_frame=0)
    run_select(landmarks=tmp_path / "lost0.npz", output=tmp_path / "keys.json", k=6)  # auto: a frame with them all
    assert read_keys(tmp_path / "keys.json").neutral["frame"] not in (0, 7, 30)


def test_the_template_goes_beside_the_keys_not_into_the_working_folder(small_take, tmp_path, monkeypatch):
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    out = tmp_path / "o"
    r = CliRunner().invoke(main, ["select", str(small_take / "truth_landmarks.npz"), "-o", str(out / "keys.json"),
                                  "-k", "3"])
    assert r.exit_code == 0, r.output + r.stderr
    assert (out / "targets.template.yaml").is_file() and list(cwd.iterdir()) == []

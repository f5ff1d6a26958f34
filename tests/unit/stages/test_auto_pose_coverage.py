"""auto_pose's slider coverage (issue 28): every slider of the ICT FaceKit in one of three groups."""

import numpy as np
import pytest
import yaml

from retarget_cli.io.rig import load_rig
from retarget_cli.methods.regions import REGION_PRESETS_68
from retarget_cli.methods.rigpose import project, rig_landmarks, slider_owners
from retarget_cli.stages.auto_pose import CONTOUR_68, DEFAULT_EXCLUDE, excluded_sliders, slider_coverage


@pytest.fixture(scope="module")
def ict(ict_rig_dir):
    rig = load_rig(ict_rig_dir / "rig.yaml")
    vx = np.asarray(yaml.safe_load((ict_rig_dir / "rig.yaml").read_text())["landmarks"])
    return rig, vx


def _groups(rig, vx, exclude, gaze: bool):
    names = ["brows-eyes", "mouth"]
    rows = {n: [p for p in REGION_PRESETS_68[n] if p not in CONTOUR_68] for n in names}
    excluded = excluded_sliders(rig.names, exclude)
    gaze_mask = excluded_sliders(rig.names, ["eyeLook*"]) if gaze else np.zeros(rig.n_sliders, bool)
    _, DL = rig_landmarks(rig, vx)
    owner = slider_owners(project(DL, np.eye(3)), [rows[n] for n in names])
    owner[excluded | gaze_mask] = -1  # as delta_pose's fixed
    cov = slider_coverage(rig, vx, names, rows, owner, excluded, gaze_mask)
    flat = {k: sorted(n for g in cov["regions"].values() for n in g[k]) for k in ("driven", "cannot", "excluded")}
    return cov, flat


def test_every_ict_slider_is_in_exactly_one_group(ict):
    rig, vx = ict
    cov, flat = _groups(rig, vx, DEFAULT_EXCLUDE, gaze=True)
    together = flat["driven"] + flat["cannot"] + flat["excluded"]
    assert sorted(together) == sorted(rig.names) and len(set(together)) == rig.n_sliders
    # the pupils move no landmark: they cannot be driven (whether excluded or not)
    assert flat["cannot"] == ["PupilDilate_L", "PupilDilate_R"]
    # the gaze sliders are driven from the iris; the brows, lids and mouth from the landmarks
    for name in ("eyeLookOut_L", "eyeLookIn_R", "eyeLookDown_L", "eyeBlink_L", "jawOpen", "browInnerUp_R"):
        assert name in flat["driven"]
    assert "eyeLookIn_L" in cov["regions"]["brows-eyes"]["driven"] and "jawOpen" in cov["regions"]["mouth"]["driven"]
    assert flat["excluded"] == []


def test_without_gaze_the_eyelook_sliders_are_left_at_zero_by_choice(ict):
    rig, vx = ict
    _, flat = _groups(rig, vx, [*DEFAULT_EXCLUDE, "mouthRoll*"], gaze=False)
    assert flat["excluded"] == sorted([f"eyeLook{d}_{s}" for d in ("Down", "In", "Out", "Up") for s in "LR"]
                                      + ["mouthRollLower", "mouthRollUpper"])
    assert flat["cannot"] == ["PupilDilate_L", "PupilDilate_R"]
    assert "eyeLookIn_L" not in flat["driven"] and "mouthRollLower" not in flat["driven"]


def test_a_slider_that_moves_only_skipped_landmarks_cannot_be_driven(ict):
    rig, vx = ict
    names = ["mouth"]
    rows = {"mouth": list(range(48, 68))}  # the mouth alone: the brows' and lids' sliders move none of its points
    _, DL = rig_landmarks(rig, vx)
    owner = slider_owners(project(DL, np.eye(3)), [rows["mouth"]])
    none = np.zeros(rig.n_sliders, bool)
    cov = slider_coverage(rig, vx, names, rows, owner, none, none)
    cannot = {n for g in cov["regions"].values() for n in g["cannot"]}
    assert {"browInnerUp_L", "eyeBlink_R"} <= cannot and "jawOpen" not in cannot


def test_the_ict_slider_that_moves_the_landmarks_mostly_in_depth_is_its_jaw_thrust(ict):
    # jawForward juts the chin by 0.12 inter-ocular distances and shows 0.02 of it in the front view; the
    # cheek puffs (4.3) and the pucker (2.2) show more of theirs
    from retarget_cli.methods.rigpose import DEPTH_RATIO, FRONT_68, depth_sliders
    from retarget_cli.stages.auto_pose import _depth_sliders

    rig, vx = ict
    rows = sorted({p for n in ("brows-eyes", "mouth") for p in REGION_PRESETS_68[n] if p not in CONTOUR_68})
    X0, DL = rig_landmarks(rig, vx)

    def names(mask):
        return sorted(n for n, m in zip(rig.names, mask) if m)

    assert names(depth_sliders(X0, DL, rows, FRONT_68)) == ["jawForward"]
    assert names(depth_sliders(X0, DL, rows, FRONT_68, ratio=3.0)) == ["cheekPuff_L", "cheekPuff_R", "jawForward"]
    # the stage's default; off with depth_ratio null or off
    region_rows = {"face": rows}
    assert names(_depth_sliders(rig, vx, np.arange(68), 68, region_rows, DEPTH_RATIO)) == ["jawForward"]
    assert not _depth_sliders(rig, vx, np.arange(68), 68, region_rows, None).any()
    assert not _depth_sliders(rig, vx, np.arange(68), 68, region_rows, "off").any()
    assert not _depth_sliders(rig, vx, np.arange(60), 60, region_rows, DEPTH_RATIO).any()  # not the 68 points'
    # as the stage reports it (tests/e2e/test_real_rig.py checks the stage's coverage.json): with the gaze driven
    # from the iris, jawForward is the one slider left at 0 by choice
    _, flat = _groups(rig, vx, [*DEFAULT_EXCLUDE, "jawForward"], gaze=True)
    assert flat["excluded"] == ["jawForward"] and "jawForward" not in flat["driven"]

"""Gaze on a rig (issue 28): the ICT FaceKit's iris travel, the gaze sliders' directions, and the delta fit
that holds the gaze sliders' landmark displacement as a fixed offset (a gaze down does not close the eye twice)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from retarget_cli.io.livelink import arkit_mapping
from retarget_cli.io.rig import load_rig
from retarget_cli.methods.gaze_rig import (
    DEFAULT_GAZE_RANGE,
    GAZE_ARKIT,
    GazeGains,
    gaze_sliders,
    rest_gaze,
    rig_gaze_gains,
)
from retarget_cli.methods.rigpose import delta_pose, rig_landmarks


@pytest.fixture(scope="module")
def ict(ict_rig_dir):
    rig = load_rig(ict_rig_dir / "rig.yaml")
    vx = np.asarray(yaml.safe_load((ict_rig_dir / "rig.yaml").read_text())["landmarks"])
    mapping = arkit_mapping(rig.names, rig.spec.names)
    index = {k: mapping[c][0] for k, c in GAZE_ARKIT.items()}
    return rig, vx, index


def test_ict_gaze_sliders_are_found_by_their_arkit_names(ict):
    rig, _, index = ict
    names = {GAZE_ARKIT[k]: rig.names[j] for k, j in index.items()}
    assert names["EyeLookOutLeft"] == "eyeLookOut_L" and names["EyeLookInRight"] == "eyeLookIn_R"
    assert names["EyeLookDownLeft"] == "eyeLookDown_L" and names["EyeLookUpRight"] == "eyeLookUp_R"


def test_ict_iris_travel_is_measured_on_its_eyeballs(ict):
    rig, vx, index = ict
    g = rig_gaze_gains(rig, index, ((vx[36], vx[39]), (vx[42], vx[45])))
    assert all(g.measured.values())
    for k, v in g.gain.items():
        assert np.sign(v) == k[2]  # each slider moves the iris the way its ARKit name says
        assert 0.03 < abs(v) < 0.3  # a fraction of the eye's width, not the lids' travel
    # the two eyes mirror each other
    assert g.gain[(0, 0, 1)] == pytest.approx(-g.gain[(1, 0, -1)], rel=0.05)
    # without the corners: the documented default
    d = rig_gaze_gains(rig, index)
    assert not any(d.measured.values()) and {abs(v) for v in d.gain.values()} == {DEFAULT_GAZE_RANGE}


def test_actor_looking_to_their_left_drives_look_out_left_and_look_in_right(ict):
    rig, _, index = ict
    gains = GazeGains(index, {k: k[2] * 0.1 for k in index}, {k: True for k in index})
    offset = np.zeros((3, 2, 2))
    offset[1, :, 0] = 0.05    # both irises toward the image's right: the actor looks to their left
    offset[2, :, 1] = -0.2    # up, beyond the rig's range: clipped at 1
    W = gaze_sliders(offset, np.zeros((2, 2)), gains, rig.n_sliders)
    n = {name: j for j, name in enumerate(rig.names)}
    assert np.allclose(W[0], 0.0)
    assert W[1, n["eyeLookOut_L"]] == pytest.approx(0.5) and W[1, n["eyeLookIn_R"]] == pytest.approx(0.5)
    assert W[1, [n["eyeLookIn_L"], n["eyeLookOut_R"], n["eyeLookUp_L"], n["eyeLookDown_L"]]].max() == 0
    assert W[2, n["eyeLookUp_L"]] == 1.0 and W[2, n["eyeLookUp_R"]] == 1.0 and W[2, n["eyeLookDown_L"]] == 0
    # the rest gaze is "ahead": an actor whose irises sit off-centre at rest drives nothing there
    rest = np.array([[0.05, 0.02], [0.05, 0.02]])
    assert np.allclose(gaze_sliders(np.tile(rest, (4, 1, 1)), rest, gains, rig.n_sliders), 0.0)


def test_rest_gaze_is_the_median_of_the_rest_frames_seen():
    g = np.zeros((10, 2, 2))
    g[:, 0, 0] = np.arange(10) / 10
    valid = np.ones((10, 2), bool)
    valid[2, 0] = False
    assert rest_gaze(g, valid, [1, 2, 3])[0, 0] == pytest.approx(0.2)  # frames 1 and 3 (2 not seen)
    assert rest_gaze(g)[0, 0] == pytest.approx(0.45)


def _observe(rig, vx, w, scale=40.0):
    """The rig's landmark vertices posed at *w* (K, n), seen from the front (y down), pixels."""
    X0, DL = rig_landmarks(rig, vx)
    X = X0[None] + np.einsum("lan,kn->kla", DL, w)
    return np.stack([X[..., 0], -X[..., 1]], axis=-1) * scale + 300.0


def test_gaze_down_preset_is_not_fitted_again_as_a_blink(ict):
    """ICT's eyeLookDown lowers the lids: with the gaze set first (preset) the fit adds no blink or squint."""
    rig, vx, index = ict
    n = {name: j for j, name in enumerate(rig.names)}
    w = np.zeros((1, rig.n_sliders))
    w[0, n["eyeLookDown_L"]] = w[0, n["eyeLookDown_R"]] = 0.8
    Y0 = _observe(rig, vx, np.zeros((1, rig.n_sliders)))[0]
    Y = _observe(rig, vx, w)
    gaze = np.zeros(rig.n_sliders, bool)
    gaze[list(index.values())] = True
    eyes = list(range(17, 27)) + list(range(36, 48))
    lids = [n[s] for s in ("eyeBlink_L", "eyeBlink_R", "eyeSquint_L", "eyeSquint_R")]
    alone = delta_pose(rig, vx, Y0, Y, regions={"eyes": eyes}, fixed=gaze)
    held = delta_pose(rig, vx, Y0, Y, regions={"eyes": eyes}, fixed=gaze, preset=w)
    # without the preset the lids' drop is read as closing the eyes ...
    assert alone["w"][0, lids].max() > 0.15
    # ... with it, nothing is left to fit and the gaze sliders come back as set
    assert held["w"][0, lids].max() < 0.02
    assert held["w"][0, n["eyeLookDown_L"]] == pytest.approx(0.8)
    assert held["rms"][0] < alone["rms"][0]

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


def test_ict_gaze_shapes_turn_no_eyeball_so_it_takes_the_default_travel(ict):
    """The ICT's eyeballs (vertices 21451-24590) are turned by a transform; its eyeLook shapes move the skin."""
    rig, vx, index = ict
    for j in index.values():
        assert np.abs(rig.D[21451 * 3:24591 * 3, [j]]).max() == 0
    g = rig_gaze_gains(rig, index, ((vx[36], vx[39]), (vx[42], vx[45])))
    assert not any(g.measured.values())
    assert all(v == k[2] * DEFAULT_GAZE_RANGE for k, v in g.gain.items())


def _eyeball_rig(angle=0.35, radius=1.2, width=3.0):
    """Two spheres (eyeballs) between corner vertices, turned by +-angle about y (in/out) and x (up/down) by
    eight shapes in ARKit naming; the corners and a lid strip stay put."""
    rng = np.random.default_rng(0)
    S = rng.normal(size=(200, 3))
    S = radius * S / np.linalg.norm(S, axis=1)[:, None]
    V, D, names = [], [], []
    centres = {"R": np.array([-3.0, 0.0, 0.0]), "L": np.array([3.0, 0.0, 0.0])}
    for c in centres.values():
        V += [c + S, c + np.array([[-width / 2, 0, radius], [width / 2, 0, radius]])]
    X = np.concatenate(V)
    corners = ((200, 201), (402, 403))  # the actor's right eye (image left) is the character's _R

    def turned(side, axis, a):
        c = centres[side]
        ca, sa = np.cos(a), np.sin(a)
        R = (np.array([[ca, 0, sa], [0, 1, 0], [-sa, 0, ca]]) if axis == "y"
             else np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]]))
        out = np.zeros_like(X)
        rows = slice(0, 200) if side == "R" else slice(202, 402)
        out[rows] = (X[rows] - c) @ R.T + c - X[rows]
        return out

    # +z faces the viewer, x toward the image's right: turning about +y by +a moves the front toward +x
    for side in "RL":
        toward_nose = 1.0 if side == "R" else -1.0
        for name, axis, a in (("In", "y", toward_nose * angle), ("Out", "y", -toward_nose * angle),
                              ("Up", "x", -angle), ("Down", "x", angle)):
            D.append(turned(side, axis, a))
            names.append(f"eyeLook{name}_{side}")
    from retarget_cli.methods.rig import BlendshapeRig

    return BlendshapeRig(X, np.stack(D), names), corners


def test_a_rig_whose_shapes_turn_its_eyeballs_gets_its_own_travel():
    rig, corners = _eyeball_rig()
    mapping = arkit_mapping(rig.names)
    index = {k: mapping[c][0] for k, c in GAZE_ARKIT.items()}
    g = rig_gaze_gains(rig, index, corners)
    assert all(g.measured.values())
    # the front half of a sphere of radius 1.2 turned by 0.35 rad moves by about 0.75 * 1.2 sin 0.35 = 0.31,
    # over an eye width of 3: about 0.1 eye widths, each slider the way its name says
    for k, v in g.gain.items():
        assert np.sign(v) == k[2] and 0.07 < abs(v) < 0.14


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


def _take_with_gaze(T=12, L=68):
    from types import SimpleNamespace

    rng = np.random.default_rng(1)
    g = 0.05 * rng.standard_normal((T, 2, 2))
    return SimpleNamespace(gaze=g, gaze_valid=np.ones((T, 2), bool), n_points=L,
                           stabilized=np.zeros((T, L, 2), np.float32) + rng.normal(0, 0.01, (T, L, 2)),
                           confidence=np.ones((T, L)))


def test_gaze_auto_drives_only_a_rig_whose_gaze_shapes_turn_its_eyeballs(ict):
    from types import SimpleNamespace

    from retarget_cli.stages.auto_pose import _gaze_preset

    rig, vx, index = ict
    lm = _take_with_gaze()
    auto = _gaze_preset("auto", "delta", lm, rig, rig.spec, np.arange(68), vx)
    on = _gaze_preset("on", "delta", lm, rig, rig.spec, np.arange(68), vx)
    assert auto[0] is None and not auto[1].any()  # the ICT's eyeLook shapes move skin only: left to the fit's 0
    assert on[0] is not None and on[1].sum() == 8 and np.abs(on[0]).max() > 0
    eyes, corners = _eyeball_rig()
    vx2 = np.zeros(68, np.int64)
    vx2[[36, 39, 42, 45]] = [corners[0][0], corners[0][1], corners[1][0], corners[1][1]]
    P, mask = _gaze_preset("auto", "delta", lm, eyes, SimpleNamespace(names={}), np.arange(68), vx2)
    assert P is not None and mask.sum() == 8  # its shapes turn the eyeballs: driven

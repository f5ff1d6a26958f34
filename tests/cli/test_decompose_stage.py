"""The decompose stage: weights.npz contents, lost frames, delta storage and bad input."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.atomic import load_npz, savez
from retarget_cli.io.landmarks import load_landmarks
from retarget_cli.io.stagefiles import load_weights, write_keys
from retarget_cli.synth.take import SOURCE_REGIONS

MOUTH = list(range(48, 68))


@pytest.fixture
def take(small_take):
    """landmarks.npz (the true landmarks of the small take) and a keys.json with two regions."""
    lm = small_take / "truth_landmarks.npz"
    keys = small_take / "keys.json"
    write_keys(keys, lm, {
        "mouth": {"points": MOUTH, "method": "manual", "frames": [0, 7, 19, 33, 48], "error": 0.0},
        "brows": {"points": list(range(17, 27)), "method": "manual", "frames": [0, 12, 40], "error": 0.0},
    })
    return small_take, lm, keys


def invoke(*args):
    return CliRunner().invoke(main, ["decompose", *map(str, args)])


def test_weights_file_has_diagnostics_and_summary(take):
    d, lm, keys = take
    out = d / "w.npz"
    r = invoke(lm, keys, "-o", out)
    assert r.exit_code == 0, r.output + r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == str(out)
    assert lines[1].split()[:4] == ["region", "residual", "px", "cardinality"]
    assert {ln.split()[0] for ln in lines[2:]} == {"brows", "mouth"}
    data = load_npz(out)
    assert data["mouth_cardinality"].dtype == np.int64 and data["mouth_cardinality"].shape == (60,)
    assert data["mouth_lost"].dtype == bool and not data["mouth_lost"].any()
    regions, meta = load_weights(out)
    assert sorted(regions) == ["brows", "mouth"]  # the diagnostics are not mistaken for regions
    diag = meta["diagnostics"]["mouth"]
    W = regions["mouth"][0]
    assert diag["mean_cardinality"] == pytest.approx(np.mean(np.sum(W > 0.01, axis=1)), rel=1e-5)
    assert diag["jitter"] == pytest.approx(np.mean(np.diff(W, n=2, axis=0) ** 2), rel=1e-5)
    assert diag["lost_frames"] == 0 and W.min() >= 0


def test_delta_weights_are_stored_in_whole_face_form(take):
    d, lm, keys = take
    out = d / "w.npz"
    r = invoke(lm, keys, "-o", out, "--solver", "sparse", "--formulation", "delta", "--neutral-frame", "0")
    assert r.exit_code == 0, r.stderr
    regions, meta = load_weights(out)
    W, frames, res = regions["mouth"]
    assert meta["formulation"] == "delta"
    stab = load_landmarks(lm).stabilized[:, MOUTH].reshape(60, -1).astype(float)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-9)  # neutral column = 1 - sum of the others
    np.testing.assert_allclose(np.linalg.norm(stab - W @ stab[frames], axis=1), res, atol=1e-6)
    assert W[0, 0] == pytest.approx(1.0, abs=1e-6)  # the neutral frame is the neutral key


def test_delta_needs_the_neutral_frame_among_the_keys(take):
    d, lm, keys = take
    r = invoke(lm, keys, "-o", d / "w.npz", "--formulation", "delta", "--neutral-frame", "5")
    assert r.exit_code == 1
    assert "neutral_frame 5 among the key frames" in r.stderr


def test_lost_frames_are_interpolated_and_flagged(take):
    d, lm, keys = take
    data = load_npz(lm)
    data["confidence"][20:25, MOUTH[:15]] = 0.0  # 15 of 20 mouth landmarks lost in frames 20..24
    data["stabilized"][20:25, MOUTH[:15]] += 40.0  # ... and wrong there
    savez(lm, data)
    out = d / "w.npz"
    r = invoke(lm, keys, "-o", out)
    assert r.exit_code == 0, r.stderr
    f = load_npz(out)
    lost = f["mouth_lost"]
    assert list(np.flatnonzero(lost)) == [20, 21, 22, 23, 24]
    assert not f["brows_lost"].any()
    W = f["mouth"]
    for t in range(20, 25):
        np.testing.assert_allclose(W[t], W[19] + (t - 19) / 6 * (W[25] - W[19]), atol=1e-12)
    assert json.loads(str(f["meta"]))["diagnostics"]["mouth"]["lost_frames"] == 5


def test_nan_landmarks_are_lost_when_their_confidence_is_zero_and_an_error_otherwise(take):
    d, lm, keys = take
    data = load_npz(lm)
    data["stabilized"][30, 50] = np.nan
    data["confidence"][30, 50] = 0.0
    savez(lm, data)
    assert invoke(lm, keys, "-o", d / "w.npz").exit_code == 0
    data["confidence"][30, 50] = 1.0
    savez(lm, data)
    r = invoke(lm, keys, "-o", d / "w.npz")
    assert r.exit_code == 1
    assert "landmark 50 of region 'mouth' is NaN in frame 30" in r.stderr and len(r.stderr.splitlines()) == 1


def test_key_frames_outside_the_take_are_an_error(take):
    d, lm, keys = take
    write_keys(keys, lm, {"mouth": {"points": MOUTH, "method": "manual", "frames": [0, 75], "error": 0.0}})
    r = invoke(lm, keys, "-o", d / "w.npz")
    assert r.exit_code == 1
    assert "key frame 75 is outside the take (60 frames" in r.stderr


def test_region_with_too_few_landmarks_is_an_error(take):
    d, lm, keys = take
    write_keys(keys, lm, {"eye": {"points": [36, 37], "method": "manual", "frames": [0, 3, 9, 14, 22, 30], "error": 0.0}})
    r = invoke(lm, keys, "-o", d / "w.npz")
    assert r.exit_code == 1
    assert "region 'eye' has 2 landmarks (4 coordinates) for 6 keys; expected at least 3 landmarks" in r.stderr


@pytest.mark.parametrize("solver", ["ls", "bounded", "ridge-clipped", "temporal", "temporal-causal", "sequential"])
def test_every_solver_runs_through_the_stage(take, solver):
    d, lm, keys = take
    r = invoke(lm, keys, "-o", d / "w.npz", "--solver", solver, "--no-summary")
    assert r.exit_code == 0, r.stderr
    assert r.stdout.strip() == str(d / "w.npz")
    assert load_weights(d / "w.npz")[1]["solver"] == solver


def test_regions_of_the_synthetic_source_are_accepted(take):
    # The synthetic take's own region definitions decompose with the default settings.
    d, lm, keys = take
    regions = {n: {"points": list(p), "method": "manual", "frames": [0, 10, 20, 30], "error": 0.0}
               for n, p in SOURCE_REGIONS.items()}
    write_keys(keys, lm, regions)
    assert invoke(lm, keys, "-o", d / "w.npz").exit_code == 0

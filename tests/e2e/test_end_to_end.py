"""End to end: synthetic take -> `retarget run` -> OBJ sequence vs ground truth."""

import hashlib

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.atomic import load_npz
from retarget_cli.io.obj import read_obj

#: Mean vertex error of the retargeted sequence relative to the mean vertex
#: displacement of the ground-truth expressions (stated in the README).
RELATIVE_TOLERANCE = 0.15
#: Mean landmark tracking error in pixels on the synthetic take.
TRACK_TOLERANCE_PX = 1.0


def digest(paths):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("take")
    r = CliRunner().invoke(main, ["synth", str(d), "--frames", "120", "--size", "256x256", "--seed", "3"])
    assert r.exit_code == 0, r.output + str(r.exception)
    r = CliRunner().invoke(main, ["run", str(d / "config.yaml")])
    assert r.exit_code == 0, r.output + str(r.exception)
    return d


def test_tracking_matches_ground_truth(run_dir):
    got = load_npz(run_dir / "out" / "landmarks.npz")
    truth = load_npz(run_dir / "truth_landmarks.npz")
    err = np.linalg.norm(got["points"] - truth["points"], axis=2)
    assert err.mean() < TRACK_TOLERANCE_PX, f"mean tracking error {err.mean():.3f} px"
    # Head motion: rotation within 1 degree and scale within 2 % in every frame.
    def rot_scale(h):
        return np.degrees(np.arctan2(h[:, 1, 0], h[:, 0, 0])), np.hypot(h[:, 0, 0], h[:, 1, 0])

    (r_got, s_got), (r_true, s_true) = rot_scale(got["head"]), rot_scale(truth["head"])
    assert np.abs(r_got - r_true).max() < 1.0
    assert np.abs(s_got / s_true - 1).max() < 0.02


def test_retargeted_sequence_matches_ground_truth_animation(run_dir):
    frames = sorted((run_dir / "out" / "frames").glob("frame_*.obj"))
    assert [f.name for f in frames] == [f"frame_{t:05d}.obj" for t in range(120)]
    truth = load_npz(run_dir / "truth.npz")["target"].astype(np.float64)
    neutral = read_obj(run_dir / "target" / "neutral.obj")
    got = np.stack([read_obj(f).vertices for f in frames])
    displacement = np.linalg.norm(truth - neutral.vertices, axis=2).mean()
    error = np.linalg.norm(got - truth, axis=2).mean()
    assert displacement > 0
    assert error / displacement < RELATIVE_TOLERANCE, f"relative error {error / displacement:.3f}"
    # Everything but the v lines is the target's, byte for byte.
    src = [ln for ln in (run_dir / "target" / "neutral.obj").read_bytes().splitlines() if not ln.startswith(b"v ")]
    out = [ln for ln in frames[57].read_bytes().splitlines() if not ln.startswith(b"v ")]
    assert src == out


def test_second_run_skips_every_stage_and_changes_nothing(run_dir):
    out = run_dir / "out"
    files = sorted(p for p in out.rglob("*") if p.is_file() and ".retarget" not in p.parts)
    before = digest(files)
    r = CliRunner().invoke(main, ["-v", "run", str(run_dir / "config.yaml")])
    assert r.exit_code == 0, r.output
    status = [ln for ln in r.stderr.splitlines() if ln.endswith((": ran", ": skipped"))]
    assert status and all(ln.endswith(": skipped") for ln in status), r.stderr
    assert digest(files) == before


def test_changed_setting_reruns_from_that_stage_only(run_dir, tmp_path):
    r = CliRunner().invoke(main, ["run", str(run_dir / "config.yaml"), "--set", "decompose.solver=ls",
                                  "--until", "decompose"])
    assert r.exit_code == 0, r.output
    assert "track: skipped" in r.stderr and "select: skipped" in r.stderr and "decompose: ran" in r.stderr
    # Restore so the module's other tests see the nnls results.
    r = CliRunner().invoke(main, ["run", str(run_dir / "config.yaml")])
    assert "decompose: ran" in r.stderr and "apply: " in r.stderr


def test_rerun_after_forced_run_is_byte_identical(run_dir):
    out = run_dir / "out"
    files = sorted(p for p in out.rglob("*") if p.is_file() and ".retarget" not in p.parts)
    before = digest(files)
    r = CliRunner().invoke(main, ["run", str(run_dir / "config.yaml"), "--force"])
    assert r.exit_code == 0, r.output
    assert digest(files) == before

"""`retarget edit` and `retarget auto-pose` through the CLI."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from retarget_cli.cli.commands import main
from retarget_cli.io.editfiles import read_animation
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.rig import load_rig
from retarget_cli.io.stagefiles import read_targets, write_keys
from retarget_cli.synth.take import expression_curves, landmark_rig

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture()
def sample(tmp_path):
    for name in ("rig.yaml", "truth.npz"):
        shutil.copy(SAMPLE / name, tmp_path / name)
    shutil.copytree(SAMPLE / "target", tmp_path / "target")
    return tmp_path


def test_edit_pins_a_vertex_and_writes_weights_and_objs(sample):
    rig = load_rig(sample / "rig.yaml")
    names, W, frames, _ = read_animation(sample / "truth.npz")
    v = int(np.argmax(np.linalg.norm(rig.evaluate(W[30:51]).std(0), axis=1)))  # moves most in frames 30-50
    u = int(np.argmax(rig.evaluate(W[60:81])[:, :, 1].std(0)))  # moves most in y in frames 60-80
    goal = rig.evaluate(W[40])[v]
    (sample / "edits.yaml").write_text(f"""rig: rig.yaml
edits:
  - pin:
      frames: [30, 50]
      ease_in: 5
      ease_out: 5
      constraints:
        - {{vertex: {v}, position: [{goal[0]}, {goal[1]}, {goal[2]}]}}
  - attenuate:
      frames: [60, 80]
      select:
        - {{vertices: [{u}], axes: y}}
""")
    res = run("edit", sample / "truth.npz", sample / "edits.yaml", "-o", sample / "out.csv", "--objs", sample / "objs")
    assert res.exit_code == 0, res.output
    names2, W2, frames2, _ = read_animation(sample / "out.csv")
    assert names2 == names and np.array_equal(frames2, frames)
    np.testing.assert_allclose(W2[:24], W[:24], atol=1e-6)  # before the ease-in: untouched
    np.testing.assert_allclose(W2[86:], W[86:], atol=1e-6)
    held = rig.evaluate(W2[30:51])[:, v]
    drift = np.linalg.norm(rig.evaluate(W[30:51])[:, v] - goal, axis=1)
    assert np.linalg.norm(held - goal, axis=1).max() < 0.1 * drift.max()
    free = abs(rig.evaluate(W[60:81])[:, u, 1] - rig.evaluate(W[60])[u, 1]).max()
    kept = abs(rig.evaluate(W2[60:81])[:, u, 1] - rig.evaluate(W2[60])[u, 1]).max()
    assert kept < 0.05 * free
    objs = sorted((sample / "objs").glob("frame_*.obj"))
    assert len(objs) == len(W)
    np.testing.assert_allclose(read_obj(objs[40]).vertices, rig.evaluate(W2[40]), atol=2e-5)
    # NPZ round trip, and the same inputs give the same bytes
    assert run("edit", sample / "truth.npz", sample / "edits.yaml", "-o", sample / "a.npz").exit_code == 0
    assert run("edit", sample / "truth.npz", sample / "edits.yaml", "-o", sample / "b.npz").exit_code == 0
    assert (sample / "a.npz").read_bytes() == (sample / "b.npz").read_bytes()
    np.testing.assert_allclose(read_animation(sample / "a.npz")[1], W2, atol=1e-6)


@pytest.mark.parametrize("body, message", [
    ("edits:\n  - pin: {frames: [1, 2], constraints: [{vertex: 99999}]}",
     r"edits\[0\].pin.constraints\[0\].vertex: vertex 99999 is outside the mesh \(2688 vertices"),
    ("edits:\n  - pin: {frames: [1, 2], constraints: [{vertex: 3, postion: [0, 0, 0]}]}",
     r"unknown key 'postion'; did you mean 'position'"),
    ("edits:\n  - pinn: {frames: 3}", r"edits\[0\]: unknown key 'pinn'; did you mean 'pin'"),
    ("edits:\n  - attenuate: {frames: [500, 510], select: [{vertices: [1]}]}",
     r"frames: \[500, 510\] is outside the animation \(frames 0-239\)"),
    ("edits:\n  - pin: {frames: 3, w0: {smile: 1}, constraints: [{vertex: 3}]}",
     r"w0: unknown expression 'smile'"),
    ("edits:\n  - attenuate: {frames: 3, select: [{vertices: [1], axes: q}]}", r"axes: expected a combination"),
])
def test_bad_edits_are_one_line_errors(sample, body, message):
    import re

    (sample / "edits.yaml").write_text("rig: rig.yaml\n" + body + "\n")
    res = run("edit", sample / "truth.npz", sample / "edits.yaml", "-o", sample / "out.csv")
    assert res.exit_code == 1
    assert re.search(message, res.output), res.output
    assert not (sample / "out.csv").exists()


def test_edit_rejects_unknown_sliders_in_the_animation(sample):
    (sample / "anim.csv").write_text("frame,smile,jaw_opn\n0,0.1,0.2\n1,0.2,0.3\n")
    (sample / "edits.yaml").write_text("edits:\n  - attenuate: {frames: 0, select: [{vertices: [1]}]}\n")
    res = run("edit", sample / "anim.csv", sample / "edits.yaml", "--rig", sample / "rig.yaml", "-o", sample / "o.csv")
    assert res.exit_code == 1 and "slider 'jaw_opn' is not a shape" in res.output and "'jaw_open'" in res.output


def test_auto_pose_recovers_the_sliders_of_synthetic_keys(tmp_path):
    L = landmark_rig(seed=1)
    (tmp_path / "shapes").mkdir()
    (tmp_path / "neutral.obj").write_bytes(format_obj(L["vertices"], L["faces"]))
    lines = ["neutral: neutral.obj", "shapes:"]
    for name, d in zip(L["names"], L["deltas"]):
        (tmp_path / "shapes" / f"{name}.obj").write_bytes(format_obj(L["vertices"] + d, L["faces"]))
        lines.append(f"  {name}: shapes/{name}.obj")
    (tmp_path / "rig.yaml").write_text("\n".join(lines) + "\n")
    (tmp_path / "map.txt").write_text("".join(f"{v}\n" for v in L["landmark_vertices"]))
    rig = load_rig(tmp_path / "rig.yaml")
    T = 60
    curves = expression_curves(T, seed=4)
    R = Rotation.from_euler("xyz", [180 - 5, 8, 3], degrees=True).as_matrix()
    pts = np.stack([140 * (rig.evaluate(c)[L["landmark_vertices"]] @ R.T)[:, :2] + [150, 160] for c in curves])
    head = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (T, 1, 1))
    save_landmarks(tmp_path / "lm.npz", Landmarks(pts, np.ones((T, 68)), head, pts))
    keys = sorted(int(f) for f in np.argsort(-curves.sum(1))[:4]) + [0]
    write_keys(tmp_path / "keys.json", tmp_path / "lm.npz",
               {"face": {"points": list(range(68)), "method": "test", "frames": keys, "error": 0.0}})
    res = run("auto-pose", tmp_path / "keys.json", tmp_path / "lm.npz", tmp_path / "rig.yaml", "--fit", "absolute",
              "--exclude", "none", "--landmark-vertices", tmp_path / "map.txt", "-o", tmp_path / "targets")
    assert res.exit_code == 0, res.output
    names, W, frames, _ = read_animation(tmp_path / "targets" / "sliders.csv")
    assert list(frames) == sorted(keys) and names == list(L["names"])
    np.testing.assert_allclose(W, curves[sorted(keys)], atol=0.01)
    tg = read_targets(tmp_path / "targets" / "targets.yaml")
    assert sorted(tg.regions["face"]["keys"]) == sorted(keys) and tg.neutral.resolve() == (tmp_path / "neutral.obj")
    f = keys[0]
    np.testing.assert_allclose(read_obj(tg.regions["face"]["keys"][f]).vertices, rig.evaluate(curves[f]), atol=0.01)
    # a map naming a vertex the mesh does not have
    (tmp_path / "bad.txt").write_text("3 99999\n")
    res = run("auto-pose", tmp_path / "keys.json", tmp_path / "lm.npz", tmp_path / "rig.yaml",
              "--landmark-vertices", tmp_path / "bad.txt", "-o", tmp_path / "t2")
    assert res.exit_code == 1 and "vertex 99999 is outside the mesh" in res.output

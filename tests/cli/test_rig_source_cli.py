"""A .glb character as the rig of auto-pose, apply, edit and pose-keys, through the CLI, against the same rig as OBJs.

The rig is the synthetic landmark rig of `retarget synth` (landmark_rig), written once as OBJs and once as a GLB
by the writer of `apply --format glb`; the landmarks are its own vertices seen by a camera.
"""

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from retarget_cli.cli.commands import main
from retarget_cli.io.atomic import savez
from retarget_cli.io.editfiles import read_animation
from retarget_cli.io.exports import rig_shapes
from retarget_cli.io.gltf import write_glb
from retarget_cli.io.landmarks import Landmarks, load_landmarks, save_landmarks
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.rig import load as rigload
from retarget_cli.io.rig import load_rig
from retarget_cli.io.rig.gltf import read_gltf_rig
from retarget_cli.io.stagefiles import read_targets, write_keys
from retarget_cli.synth.take import expression_curves, landmark_rig


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """OBJ rig (rig.yaml), the same rig as char.glb (glb.yaml: source + landmarks), 60 frames of its landmarks."""
    d = tmp_path_factory.mktemp("glb_take")
    L = landmark_rig(seed=1)
    (d / "shapes").mkdir()
    (d / "neutral.obj").write_bytes(format_obj(L["vertices"], L["faces"]))
    lines = ["neutral: neutral.obj", "shapes:"]
    for name, delta in zip(L["names"], L["deltas"]):
        (d / "shapes" / f"{name}.obj").write_bytes(format_obj(L["vertices"] + delta, L["faces"]))
        lines.append(f"  {name}: shapes/{name}.obj")
    (d / "map.txt").write_text("".join(f"{v}\n" for v in L["landmark_vertices"]))
    (d / "rig.yaml").write_text("\n".join(lines + ["landmarks: map.txt"]) + "\n")
    objs = load_rig(d / "rig.yaml")
    shapes, names, W = rig_shapes(objs, np.zeros((1, objs.n_sliders)))  # what apply --format glb writes
    write_glb(d / "char.glb", base=objs.neutral, faces=L["faces"], targets=shapes, target_names=names, weights=W,
              fps=30.0)
    (d / "glb.yaml").write_text("source: char.glb\nlandmarks: map.txt\n")
    T = 60
    curves = expression_curves(T, seed=4)
    R = Rotation.from_euler("xyz", [180 - 5, 8, 3], degrees=True).as_matrix()
    pts = np.stack([140 * (objs.evaluate(c)[L["landmark_vertices"]] @ R.T)[:, :2] + [150, 160] for c in curves])
    head = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (T, 1, 1))
    save_landmarks(d / "lm.npz", Landmarks(pts, np.ones((T, 68)), head, pts))
    keys = sorted(int(f) for f in np.argsort(-curves.sum(1))[:5]) + [0]
    write_keys(d / "keys.json", d / "lm.npz",
               {"face": {"points": list(range(68)), "method": "test", "frames": sorted(set(keys)), "error": 0.0}})
    savez(d / "poses.npz", {"curves": curves, "names": np.array(objs.names)})
    res = run("decompose", d / "lm.npz", d / "keys.json", "--formulation", "delta", "-o", d / "weights.npz")
    assert res.exit_code == 0, res.output
    return d


def test_auto_pose_and_apply_on_the_glb_equal_the_objs(take):
    curves = {}
    for rig in ("rig.yaml", "glb.yaml"):
        out = take / rig.replace(".yaml", "")
        res = run("auto-pose", take / "keys.json", take / "lm.npz", take / rig, "-o", out / "targets")
        assert res.exit_code == 0, res.output
        res = run("apply", take / "weights.npz", out / "targets" / "targets.yaml", "--format", "curves,obj,glb",
                  "-o", out / "frames")
        assert res.exit_code == 0, res.output
        names, C, _, _ = read_animation(out / "frames" / "curves.npz")
        curves[rig] = (names, C)
    assert curves["rig.yaml"][0] == curves["glb.yaml"][0]
    assert curves["rig.yaml"][1].max() > 0.1
    np.testing.assert_allclose(curves["glb.yaml"][1], curves["rig.yaml"][1], rtol=0, atol=1e-4)
    tg = read_targets(take / "glb" / "targets" / "targets.yaml")
    assert tg.neutral == take / "glb" / "targets" / "neutral.obj" and tg.rig.resolve() == take / "glb.yaml"
    rig = load_rig(take / "glb.yaml")
    np.testing.assert_allclose(read_obj(tg.neutral).vertices, rig.neutral, atol=5e-7)
    a = read_obj(take / "rig" / "frames" / "frame_00030.obj").vertices
    b = read_obj(take / "glb" / "frames" / "frame_00030.obj").vertices
    np.testing.assert_allclose(b, a, atol=1e-4)
    back = read_gltf_rig(take / "glb" / "frames" / "animation.glb")  # the glb export of the glb rig reads back
    assert back.target_names == list(rig.names) and len(back.neutral) >= rig.n_vertices


def test_edit_and_pose_keys_take_the_glb(take):
    (take / "edits.yaml").write_text("edits:\n  - attenuate: {frames: [0, 10], select: [{vertices: [1, 2]}]}\n")
    res = run("edit", take / "poses.npz", take / "edits.yaml", "--rig", take / "char.glb", "-o", take / "e.npz",
              "--objs", take / "edit_objs")
    assert res.exit_code == 0, res.output
    assert (take / "edit_objs" / "frame_00000.obj").is_file()
    res = run("pose-keys", take / "keys.json", take / "char.glb", "--poses", take / "poses.npz",
              "-o", take / "posed")
    assert res.exit_code == 0, res.output
    tg = read_targets(take / "posed" / "targets.yaml")
    assert tg.neutral == take / "posed" / "neutral.obj"
    rig = load_rig(take / "char.glb")
    curves = np.load(take / "poses.npz")["curves"]
    for f, obj in tg.regions["face"]["keys"].items():
        np.testing.assert_allclose(read_obj(obj).vertices, rig.evaluate(curves[f]), rtol=0, atol=1e-6)


@pytest.mark.parametrize("rig, where", [("char.glb", "in a rig.yaml with 'source: char.glb'"),
                                        ("nomap.yaml", "in it")])
def test_auto_pose_without_a_landmark_map_names_map_landmarks(take, monkeypatch, rig, where):
    """With 68 points the map is found automatically (tests/cli/test_map_landmarks_cli.py); with another layout
    there is nothing to find it with: one line naming map-landmarks, before the rig is read."""
    (take / "nomap.yaml").write_text("source: char.glb\n")
    lm = load_landmarks(take / "lm.npz")
    pts = lm.points[:, :60]
    save_landmarks(take / "lm60.npz", Landmarks(pts, np.ones(pts.shape[:2]), lm.head, pts))
    write_keys(take / "keys60.json", take / "lm60.npz",
               {"face": {"points": list(range(60)), "method": "test", "frames": [0, 5], "error": 0.0}})
    monkeypatch.setattr(rigload, "read_character", lambda *a, **k: pytest.fail("the rig was read before the error"))
    res = run("auto-pose", take / "keys60.json", take / "lm60.npz", take / rig, "-o", take / "t")
    assert res.exit_code == 1, res.output
    line = res.output.strip()
    assert "\n" not in line and "Traceback" not in line
    assert f"'retarget map-landmarks {take / rig} -o map.txt'" in line and "'landmarks: map.txt'" in line
    assert where in line and not (take / "t").exists()


def test_run_reruns_auto_pose_when_the_glb_changes(take, tmp_path):
    for name in ("keys.json", "lm.npz", "glb.yaml", "char.glb", "map.txt"):
        (tmp_path / name).write_bytes((take / name).read_bytes())
    cfg = {"output_dir": "out", "auto_pose": {"keys": "keys.json", "landmarks": "lm.npz", "rig": "glb.yaml"}}
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    res = run("run", tmp_path / "cfg.yaml")
    assert res.exit_code == 0, res.output
    res = run("run", tmp_path / "cfg.yaml")
    assert res.exit_code == 0 and "ran" not in res.output.replace("skipped", ""), res.output
    glb = tmp_path / "char.glb"
    glb.write_bytes(glb.read_bytes() + b"\0" * 4)  # bytes after the GLB's declared length: a changed file, same rig
    res = run("run", tmp_path / "cfg.yaml")
    assert res.exit_code == 0 and "ran" in res.output.replace("skipped", ""), res.output

"""A USD character as the rig of auto-pose and apply through the CLI, against the same rig as OBJs; corrupt USD and
FBX rigs are one line.

The rig is the synthetic landmark rig of `retarget synth` (landmark_rig), written once as OBJs and once as USD by
the writer of `apply --format usd`; the landmarks are its own vertices seen by a camera.
"""

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from retarget_cli.cli.commands import main
from retarget_cli.io.editfiles import read_animation
from retarget_cli.io.exports import rig_shapes
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.obj import format_obj
from retarget_cli.io.rig import load_rig
from retarget_cli.io.stagefiles import write_keys
from retarget_cli.io.usd import write_usd_skel
from retarget_cli.synth.take import expression_curves, landmark_rig

pytest.importorskip("pxr", reason="usd-core (the 'usd' extra) is not installed")


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """OBJ rig (rig.yaml), the same rig as char.usd (usd.yaml: source + landmarks), 60 frames of its landmarks."""
    d = tmp_path_factory.mktemp("usd_take")
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
    shapes, names, W = rig_shapes(objs, np.zeros((1, objs.n_sliders)))  # what apply --format usd writes
    faces = np.asarray(L["faces"])
    write_usd_skel(d / "char.usd", points=objs.neutral, counts=[3] * len(faces), corners=faces.ravel(), shapes=shapes,
                   names=names, weights=W, fps=30.0)
    (d / "usd.yaml").write_text("source: char.usd\nlandmarks: map.txt\n")
    T = 60
    curves = expression_curves(T, seed=4)
    R = Rotation.from_euler("xyz", [180 - 5, 8, 3], degrees=True).as_matrix()
    pts = np.stack([140 * (objs.evaluate(c)[L["landmark_vertices"]] @ R.T)[:, :2] + [150, 160] for c in curves])
    head = np.tile(np.array([[1.0, 0, 0], [0, 1.0, 0]]), (T, 1, 1))
    save_landmarks(d / "lm.npz", Landmarks(pts, np.ones((T, 68)), head, pts))
    keys = sorted(int(f) for f in np.argsort(-curves.sum(1))[:5]) + [0]
    write_keys(d / "keys.json", d / "lm.npz",
               {"face": {"points": list(range(68)), "method": "test", "frames": sorted(set(keys)), "error": 0.0}})
    res = run("decompose", d / "lm.npz", d / "keys.json", "--formulation", "delta", "-o", d / "weights.npz")
    assert res.exit_code == 0, res.output
    return d


def test_auto_pose_and_apply_on_the_usd_equal_the_objs(take):
    curves = {}
    for rig in ("rig.yaml", "usd.yaml"):
        out = take / rig.replace(".yaml", "")
        res = run("auto-pose", take / "keys.json", take / "lm.npz", take / rig, "-o", out / "targets")
        assert res.exit_code == 0, res.output
        res = run("apply", take / "weights.npz", out / "targets" / "targets.yaml", "--format", "curves",
                  "-o", out / "frames")
        assert res.exit_code == 0, res.output
        names, C, _, _ = read_animation(out / "frames" / "curves.npz")
        curves[rig] = (names, C)
    assert curves["rig.yaml"][0] == curves["usd.yaml"][0]
    assert curves["rig.yaml"][1].max() > 0.1
    np.testing.assert_allclose(curves["usd.yaml"][1], curves["rig.yaml"][1], rtol=0, atol=1e-4)
    res = run("apply", take / "weights.npz", take / "usd" / "targets" / "targets.yaml", "--format", "curves,same",
              "-o", take / "usd" / "same")
    assert res.exit_code == 0, res.output
    copy = take / "usd" / "same" / "char_animated.usd"
    assert str(copy) in res.output
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(copy))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skel/Anim"))
    names, C, frames, _ = read_animation(take / "usd" / "same" / "curves.npz")
    assert list(anim.GetBlendShapesAttr().Get()) == names
    assert anim.GetBlendShapeWeightsAttr().GetTimeSamples() == list(range(len(frames)))
    W = np.array([list(anim.GetBlendShapeWeightsAttr().Get(Usd.TimeCode(int(t)))) for t in frames])
    np.testing.assert_allclose(W, C, rtol=0, atol=1e-6)
    assert len(load_rig(copy).names) == len(names)


@pytest.mark.parametrize("name, blob", [("char.usd", b"PXR-USDC\x00\x08" + b"\x00" * 40),
                                        ("char.usda", b"#usda 1.0\n(\n  defaultPrim = \n"),
                                        ("char.fbx", b"Kaydara FBX Binary  \x00\x1a\x00" + b"\xff" * 64)])
def test_a_corrupt_character_file_is_one_line(take, tmp_path, name, blob):
    (tmp_path / name).write_bytes(blob)
    res = run("auto-pose", take / "keys.json", take / "lm.npz", tmp_path / name, "-o", tmp_path / "t")
    assert res.exit_code == 1, res.output
    line = res.output.strip()
    assert "\n" not in line and "Traceback" not in line and name in line, line
    assert not (tmp_path / "t").exists()

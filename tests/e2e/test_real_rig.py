"""Your video, your rig: 60 frames of a real clip onto the ICT FaceKit through one config.

Uses the committed real assets (sample_data/real/d3.mp4 and sample_data/ict, both MIT) through the
`real_clip` and `ict_rig_dir` fixtures of tests/conftest.py.
"""

import json
import shutil

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.editfiles import read_animation
from retarget_cli.io.obj import read_obj
from retarget_cli.io.rig import load_rig
from retarget_cli.io.stagefiles import load_weights, read_targets, read_vertex_mask


def material_vertices(obj_path, materials) -> np.ndarray:
    """0-based ids of the vertices used by faces of the given materials (usemtl) of an OBJ."""
    ids, current = set(), None
    for line in obj_path.read_text().splitlines():
        if line.startswith("usemtl "):
            current = line.split()[1]
        elif line.startswith("f ") and current in materials:
            ids.update(int(tok.split("/")[0]) - 1 for tok in line.split()[1:])
    return np.array(sorted(ids))


def invoke(*args):
    res = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return res


@pytest.fixture(scope="module")
def ict(ict_rig_dir):
    return load_rig(ict_rig_dir / "rig.yaml")


@pytest.fixture(scope="module")
def real_run(real_clip, ict_rig_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("real_run")
    cfg = {
        "output_dir": "out",
        "seed": 0,
        "track": {"video": str(real_clip / "d3.avi"), "init": str(real_clip / "d3_00000.pts")},
        "select": {"method": "greedy", "k": 6, "neutral_frame": 0, "regions": {"brows-eyes": None, "mouth": None}},
        "decompose": {"formulation": "delta"},
        "auto_pose": {"rig": str(ict_rig_dir / "rig.yaml")},
        "apply": {"formats": ["curves", "obj"]},
    }
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    res = invoke("run", d / "config.yaml")
    assert res.exit_code == 0, res.output
    return d


def test_one_config_runs_video_to_rig_curves_with_manifests(real_run):
    out = real_run / "out"
    for stage in ("track", "select", "decompose", "auto_pose", "apply"):
        man = json.loads((out / ".retarget" / f"{stage}.json").read_text())
        assert man["outputs"] and man["inputs"], stage
    res = invoke("run", real_run / "config.yaml")
    assert res.exit_code == 0 and "ran" not in res.output.replace("skipped", ""), res.output
    # the config names no solver: decompose's default, the temporal solver (issue 27)
    assert load_weights(out / "weights.npz")[1]["solver"] == "temporal"


def test_curves_are_the_rig_sliders_with_a_neutral_first_frame(real_run, ict):
    names, C, frames, times = read_animation(real_run / "out" / "frames" / "curves.csv")
    assert names == list(ict.names) and list(frames) == list(range(60)) and times is not None
    assert np.all(C >= ict.lower - 1e-9) and np.all(C <= ict.upper + 1e-9)
    assert C[0].max() < 0.05  # the actor's neutral frame poses the rig at rest
    npz = np.load(real_run / "out" / "frames" / "curves.npz")
    np.testing.assert_allclose(npz["curves"], C, atol=5e-7)
    assert list(npz["names"]) == names and list(npz["frames"]) == list(range(60))
    # the actor opens the mouth in this slice: jawOpen follows it
    assert C[:, names.index("jawOpen")].max() > 0.05


def test_the_jaw_thrust_the_landmarks_see_only_in_depth_is_left_at_zero_and_reported(real_run, ict):
    # auto_pose.depth_ratio (default 5): the ICT FaceKit's jawForward moves its landmarks 6.6 times as far in 3D as
    # the front view shows, so it is kept out of the fit; coverage.json says so
    names, C, _, _ = read_animation(real_run / "out" / "frames" / "curves.csv")
    assert np.all(C[:, names.index("jawForward")] == 0.0)
    cov = json.loads((real_run / "out" / "targets" / "coverage.json").read_text())
    excluded = [n for g in cov["regions"].values() for n in g["excluded"]]
    assert "jawForward" in excluded and "depth_ratio" in cov["rule"]
    assert "cheekPuff_L" not in excluded and "mouthPucker" not in excluded


def test_apply_drives_the_rig_with_every_frame_auto_pose_posed(real_run, ict, tmp_path):
    out = real_run / "out"
    tg = read_targets(out / "targets" / "targets.yaml")
    assert tg.curves == out / "targets" / "curves.csv"  # auto_pose.frames: all (the default)
    names, P, frames, _ = read_animation(tg.curves)
    _, C, _, _ = read_animation(out / "frames" / "curves.npz")
    assert list(frames) == list(range(60)) and names == list(ict.names)
    np.testing.assert_allclose(C, np.clip(P, ict.lower, ict.upper), atol=1e-6)
    man = json.loads((out / ".retarget" / "apply.json").read_text())
    assert any(k.endswith("targets/curves.csv") for k in man["inputs"])
    # curves of another take length are refused in one line
    short = tmp_path / "targets"
    shutil.copytree(out / "targets", short)
    data = yaml.safe_load((short / "targets.yaml").read_text())
    data.update(rig=str(tg.rig), neutral=str(tg.neutral), sliders=str(tg.sliders))
    (short / "targets.yaml").write_text(yaml.safe_dump(data))
    (short / "curves.csv").write_text("\n".join(tg.curves.read_text().splitlines()[:30]) + "\n")
    res = invoke("apply", out / "weights.npz", short / "targets.yaml", "--format", "curves", "-o", tmp_path / "f")
    assert res.exit_code == 1 and "curves.csv: 29 frames (0 to 28), the weights have frames 0 to 59" in res.output


def test_curves_reproduce_the_meshes_for_a_linear_rig(real_run, ict):
    _, C, _, _ = read_animation(real_run / "out" / "frames" / "curves.npz")
    for t in (0, 17, 42, 59):
        obj = read_obj(real_run / "out" / "frames" / f"frame_{t:05d}.obj")
        np.testing.assert_allclose(obj.vertices, ict.evaluate(C[t]), atol=1e-5)


def test_edit_and_solve_rig_read_the_outputs_as_written(real_run, ict_rig_dir, tmp_path):
    frames_dir = real_run / "out" / "frames"
    (tmp_path / "edits.yaml").write_text("edits:\n  - attenuate: {frames: [10, 30], select: [{vertices: [1225]}]}\n")
    res = invoke("edit", frames_dir / "curves.csv", tmp_path / "edits.yaml", "--rig", ict_rig_dir / "rig.yaml",
                 "-o", tmp_path / "edited.csv")
    assert res.exit_code == 0, res.output
    names, E, frames, _ = read_animation(tmp_path / "edited.csv")
    assert len(E) == 60 and len(names) == 57
    res = invoke("solve-rig", ict_rig_dir / "rig.yaml", str(frames_dir / "frame_0004[0-2].obj"),
                 "-o", tmp_path / "solved.npz")
    assert res.exit_code == 0, res.output
    solved = np.load(tmp_path / "solved.npz")
    _, C, _, _ = read_animation(frames_dir / "curves.npz")
    order = [list(names).index(str(n)) for n in solved["names"]]
    np.testing.assert_allclose(solved["curves"], C[40:43][:, order], atol=0.02)


def test_masks_derived_from_the_rig_cover_every_moving_vertex_and_teeth_follow_jaw_open(real_run, ict):
    tg = read_targets(real_run / "out" / "targets" / "targets.yaml")
    assert tg.rig is not None and tg.sliders is not None
    masks = {name: read_vertex_mask(reg["vertices"], ict.n_vertices) for name, reg in tg.regions.items()}
    owned = {name: reg["sliders"] for name, reg in tg.regions.items()}
    assert "jawOpen" in owned["mouth"] and "eyeBlink_L" in owned["brows-eyes"]
    D = np.asarray(ict.D).reshape(ict.n_vertices, 3, -1)
    moved_by_owned = np.zeros(ict.n_vertices, bool)
    for sl in owned["mouth"] + owned["brows-eyes"]:
        moved_by_owned |= np.linalg.norm(D[:, :, ict.index[sl]], axis=1) > 1e-3
    total = masks["mouth"] + masks["brows-eyes"]
    assert np.all(total[moved_by_owned] > 0.99)
    # Teeth, gums and tongue are separate shells that jawOpen carries (the lower ones).
    shells = material_vertices(tg.rig.parent / "generic_neutral_mesh.obj", {"M_Teeth", "M_GumsTongue"})
    jaw = shells[np.linalg.norm(D[shells, :, ict.index["jawOpen"]], axis=1) > 1e-2]
    assert len(jaw) > 100 and np.all(masks["mouth"][jaw] > 0.5)


def test_driving_the_key_shapes_moves_the_teeth_like_the_rig(real_run, tmp_path, ict, ict_rig_dir):
    # the key path (auto-pose --frames keys: the rig's curves interpolate the key sliders by the weights), whose
    # key shapes blended by the same weights must move the teeth as the rig does
    out = real_run / "out"
    res = invoke("auto-pose", out / "keys.json", out / "landmarks.npz", ict_rig_dir / "rig.yaml", "--frames", "keys",
                 "-o", tmp_path / "targets")
    assert res.exit_code == 0, res.output
    assert read_targets(tmp_path / "targets" / "targets.yaml").curves is None
    for drive, formats in (("rig", ("--format", "obj,curves")), ("keys", ("--format", "obj"))):
        res = invoke("apply", out / "weights.npz", tmp_path / "targets" / "targets.yaml", "--drive", drive,
                     *formats, "-o", tmp_path / drive)
        assert res.exit_code == 0, res.output
    _, C, _, _ = read_animation(tmp_path / "rig" / "curves.npz")
    t = int(np.argmax(C[:, ict.index["jawOpen"]]))
    D = np.asarray(ict.D).reshape(ict.n_vertices, 3, -1)
    teeth = material_vertices(ict_rig_dir / "generic_neutral_mesh.obj", {"M_Teeth", "M_GumsTongue"})
    shells = teeth[np.linalg.norm(D[teeth, :, ict.index["jawOpen"]], axis=1) > 1e-2]
    keys = read_obj(tmp_path / "keys" / f"frame_{t:05d}.obj").vertices[shells]
    rig = read_obj(tmp_path / "rig" / f"frame_{t:05d}.obj").vertices[shells]
    moved = np.linalg.norm(rig - ict.neutral[shells], axis=1)
    assert moved.mean() > 0.05  # cm: the teeth really open
    assert np.linalg.norm(keys - rig, axis=1).mean() < 0.1 * moved.mean()


def test_rig_landmarks_out_of_range_is_a_clear_error(real_run, ict_rig_dir, tmp_path):
    text = (ict_rig_dir / "rig.yaml").read_text().replace("landmarks: [1225,", "landmarks: [99999,")
    bad = ict_rig_dir / "rig_bad_landmarks.yaml"
    bad.write_text(text)
    out = real_run / "out"
    res = invoke("auto-pose", out / "keys.json", out / "landmarks.npz", bad, "-o", tmp_path / "t")
    assert res.exit_code == 1 and "landmarks[0] = 99999 is not a vertex" in res.output
    assert "Traceback" not in res.output

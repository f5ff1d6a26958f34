"""The ICT FaceKit as a GLB: written by `apply --format glb`, read back as the rig of `retarget run` (rig.yaml
`source:` with the kit's shipped `landmarks:`), on 60 frames of the real clip. The curves equal the OBJ rig's.

Uses sample_data/real/d3.mp4 and sample_data/ict (both MIT) through the `real_clip` and `ict_rig_dir` fixtures.
"""

import shutil

import numpy as np
import yaml
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.editfiles import read_animation
from retarget_cli.io.rig import load_rig


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_ict_through_its_glb_gives_the_obj_rigs_curves(real_clip, ict_rig_dir, tmp_path):
    cfg = {
        "output_dir": "out",
        "seed": 0,
        "track": {"video": str(real_clip / "d3.avi"), "init": str(real_clip / "d3_00000.pts")},
        "select": {"method": "greedy", "k": 6, "neutral_frame": 0, "regions": {"brows-eyes": None, "mouth": None}},
        "decompose": {"formulation": "delta"},
        "auto_pose": {"rig": str(ict_rig_dir / "rig.yaml")},
        "apply": {"formats": ["curves", "glb"]},
    }
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    res = invoke("run", tmp_path / "config.yaml")
    assert res.exit_code == 0, res.output
    frames = tmp_path / "out" / "frames"
    names, C_obj, _, _ = read_animation(frames / "curves.npz")

    # the GLB apply wrote: one morph target per slider, named as the slider; the kit's landmarks, pairs and names
    (tmp_path / "glb").mkdir()
    shutil.copy(frames / "animation.glb", tmp_path / "glb" / "ict.glb")
    shipped = yaml.safe_load((ict_rig_dir / "rig.yaml").read_text())
    rig_yaml = {"source": "ict.glb", **{k: shipped[k] for k in ("range", "landmarks", "exclusive", "names")}}
    (tmp_path / "glb" / "rig.yaml").write_text(yaml.safe_dump(rig_yaml))
    ict, glb = load_rig(ict_rig_dir / "rig.yaml"), load_rig(tmp_path / "glb" / "rig.yaml")
    N = ict.n_vertices
    assert glb.names == ict.names and glb.n_vertices >= N  # vertices split at UV seams come after the OBJ's
    np.testing.assert_allclose(glb.neutral[:N], ict.neutral, rtol=0, atol=1e-5)  # float32 in the GLB, cm
    w = np.random.default_rng(0).random(ict.n_sliders)
    np.testing.assert_allclose(glb.evaluate(w)[:N], ict.evaluate(w), rtol=0, atol=1e-4)

    cfg["auto_pose"]["rig"] = str(tmp_path / "glb" / "rig.yaml")
    cfg["apply"]["formats"] = ["curves"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    res = invoke("run", tmp_path / "config.yaml")
    assert res.exit_code == 0, res.output
    assert "auto_pose: ran" in res.output and "track: ran" not in res.output, res.output
    names_glb, C_glb, _, _ = read_animation(frames / "curves.npz")
    assert names_glb == names and C_obj.max() > 0.05
    np.testing.assert_allclose(C_glb, C_obj, rtol=0, atol=1e-4)

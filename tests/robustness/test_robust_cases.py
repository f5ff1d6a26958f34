"""Bad inputs as a hostile or careless user gives them (issue #17): each gives one line, no traceback,
a non-zero exit, leaves every input as it was and writes nothing outside the output folder.

Every case runs the CLI in-process on a private copy of a tiny synthetic take (``take/``, with the
outputs of one ``retarget run`` in ``take/out``). A case returns the command line, the texts its
one-line message must contain (the file or key it is about) and the folder writes may go to.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from conftest import snapshot

from retarget_cli.cli.commands import main


@dataclass
class Case:
    args: list
    expect: tuple  # substrings of the one-line message
    out: str = "out"  # the only folder (relative to the take) that may change
    code: int = 1


def _config(d: Path, edit) -> Path:
    cfg = yaml.safe_load((d / "config.yaml").read_text())
    edit(cfg)
    p = d / "bad.yaml"
    p.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return p


def _run(d, edit, *extra):
    return ["run", str(_config(d, edit)), *extra]


def _npz(d: Path, src: str, name: str, **changes) -> Path:
    data = dict(np.load(d / src))
    for k, v in changes.items():
        if v is None:
            data.pop(k, None)
        else:
            data[k] = v
    p = d / name
    np.savez(p, **data)
    return p


def _keys(d: Path, edit) -> Path:
    data = json.loads((d / "out" / "keys.json").read_text())
    edit(data)
    p = d / "badkeys.json"
    p.write_text(json.dumps(data))
    return p


def _pose_keys(d, keys, *masks, out="out/t2"):
    m = masks or (f"brows-eyes={d / 'target/regions/brows-eyes.txt'}", f"mouth={d / 'target/regions/mouth.txt'}")
    return ["pose-keys", str(keys), str(d / "rig.yaml"), "--poses", str(d / "truth.npz"),
            *[a for x in m for a in ("--mask", x)], "-o", str(d / out)]


def _member_bytes(d: Path, name: str, member: str, payload: bytes) -> Path:
    import zipfile

    p = d / name
    with zipfile.ZipFile(d / "out" / "landmarks.npz") as src, zipfile.ZipFile(p, "w") as dst:
        for info in src.infolist():
            dst.writestr(info.filename, payload if info.filename == member else src.read(info))
    return p


def c_csv_overwrites_pts(d):
    def edit(c):
        c["decompose"]["csv"] = "../face_00000.pts"
    return Case(_run(d, edit), ("decompose.csv", "outside output_dir"), code=2)


def c_select_output_overwrites_rig(d):
    def edit(c):
        c["select"]["output"] = "../rig.yaml"
    return Case(_run(d, edit), ("select.output", "outside output_dir"), code=2)


def c_decompose_csv_is_its_input(d):
    return Case(["decompose", str(d / "out/landmarks.npz"), str(d / "out/keys.json"), "-o", str(d / "out/w.npz"),
                 "--csv", str(d / "out/keys.json")], ("keys.json", "input"))


def c_apply_output_parent_deletes_frames(d):
    (d / "frame_99999.obj").write_text("v 0 0 0\n")  # the user's file beside the config

    def edit(c):
        c["apply"]["output"] = ".."
    return Case(_run(d, edit, "--force"), ("apply.output", "outside output_dir"), code=2)


def c_region_escapes_in_config(d):
    def edit(c):
        c["select"]["regions"] = {"../../../escaped-region": "all"}
        c["pose"]["masks"] = {"../../../escaped-region": "target/regions/mouth.txt"}
    return Case(_run(d, edit), ("bad.yaml", "select.regions", "escaped-region"), code=2)


def c_region_absolute_in_keys(d):
    region = str(d.parent / "abs-region")

    def edit(k):
        k["regions"] = {region: k["regions"]["mouth"]}
    keys = _keys(d, edit)  # one region: pose-keys needs no mask
    return Case(["pose-keys", str(keys), str(d / "rig.yaml"), "--poses", str(d / "truth.npz"), "-o",
                 str(d / "out/t2")], ("badkeys.json", "abs-region"))


def c_region_absolute_in_masks(d):
    # the --mask option's region name is checked as the setting it is, before any file is read
    region = str(d.parent / "abs-region")

    def edit(k):
        k["regions"] = {region: k["regions"]["mouth"]}
    return Case(_pose_keys(d, _keys(d, edit), f"{region}={d / 'target/regions/mouth.txt'}"),
                ("masks", "abs-region", "not a valid region name"))


def c_output_key_escapes(d):
    def edit(c):
        c["select"]["output"] = "../../x.json"
    return Case(_run(d, edit), ("select.output", "outside output_dir"), code=2)


def c_output_key_absolute(d):
    def edit(c):
        c["decompose"]["output"] = str(d.parent / "abs.npz")
    return Case(_run(d, edit), ("decompose.output", "outside output_dir"), code=2)


def c_csv_huge_point_id(d):
    (d / "big.csv").write_text("frame,point,x,y\n0,300000000,1,1\n")
    return Case(["track", str(d / "face.mp4"), "--init", str(d / "big.csv"), "-o", str(d / "out/lm.npz")],
                ("big.csv", "line 2", "too large"))


def c_pts_huge_count(d):
    (d / "big_00000.pts").write_text("version: 1\nn_points: 900000000000\n{\n1 1\n}\n")
    return Case(["track", str(d / "face.mp4"), "--init", str(d / "big_00000.pts"), "-o", str(d / "out/lm.npz")],
                ("big_00000.pts", "n_points"))


def c_section_not_mapping_with_set(d):
    def edit(c):
        c["apply"] = 5
    return Case(_run(d, edit, "--set", "apply.head_motion=none"), ("bad.yaml", "'apply'", "mapping"), code=2)


def c_yaml_alias_bomb(d):
    # 7 levels of 10 aliases: 60 bytes a line, 10^7 landmark ids once expanded
    lines = ["  rigid_points:", "    - &a0 [27, 28, 29, 30, 31, 32, 33, 34, 35, 36]"]
    lines += [f"    - &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 8)]
    text = (d / "config.yaml").read_text().replace("track:\n", "track:\n" + "\n".join(lines) + "\n", 1)
    (d / "bad.yaml").write_text(text)
    return Case(["run", str(d / "bad.yaml")], ("bad.yaml", "alias"), code=2)


def c_fps_shape(d):
    p = _npz(d, "out/landmarks.npz", "lm.npz", fps=np.array([30.0, 25.0]))
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'fps'"))


def c_fps_nonfinite(d):
    p = _npz(d, "out/landmarks.npz", "lm.npz", fps=np.array(np.inf))
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'fps'"))


def c_head_nonfinite(d):
    head = np.load(d / "out/landmarks.npz")["head"].copy()
    head[3, 0, 0] = np.nan
    p = _npz(d, "out/landmarks.npz", "lm.npz", head=head)
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'head'", "frame 3"))


def c_mask_of_objects(d):
    (d / "mask.txt").write_text('[{"a": 1}]')
    return Case(_pose_keys(d, d / "out/keys.json", f"brows-eyes={d / 'mask.txt'}",
                           f"mouth={d / 'target/regions/mouth.txt'}"), ("mask.txt",))


def c_mask_ids_out_of_range(d):
    (d / "mask.txt").write_text("0\n1\n99999999\n")
    return Case(_pose_keys(d, d / "out/keys.json", f"brows-eyes={d / 'mask.txt'}",
                           f"mouth={d / 'target/regions/mouth.txt'}"), ("mask.txt", "vertex ids"))


def c_weights_meta_list(d):
    w = _npz(d, "out/weights.npz", "w.npz", meta=np.array("[1, 2]"))
    return Case(["apply", str(w), str(d / "out/targets/targets.yaml"), "-o", str(d / "out/f2")], ("w.npz", "'meta'"))


def c_integer_region_key(d):
    def edit(c):
        c["select"]["regions"] = {5: "all"}
        c["pose"]["masks"] = {5: "target/regions/mouth.txt"}
    return Case(_run(d, edit), ("bad.yaml", "select.regions", "5"), code=2)


def c_npz_member_not_npy(d):
    return Case(["select", str(_member_bytes(d, "lm.npz", "points.npy", b"this is not npy data at all")),
                 "-o", str(d / "out/k.json")], ("lm.npz", "'points'"))


def c_npz_member_bad_header(d):
    payload = b"\x93NUMPY\x01\x00\x20\x00{'descr': '<f4', 'fortran_order': False, 'shape': (24,68 }   \n"
    return Case(["select", str(_member_bytes(d, "lm.npz", "points.npy", payload)), "-o", str(d / "out/k.json")],
                ("lm.npz", "'points'"))


def c_npz_huge_array(d):
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (100000000000, 68, 2), }"
    header += b" " * (63 - len(header) % 64) + b"\n"
    payload = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header
    return Case(["select", str(_member_bytes(d, "lm.npz", "points.npy", payload)), "-o", str(d / "out/k.json")],
                ("lm.npz", "'points'", "limit"))


def c_structured_points(d):
    pts = np.zeros((24, 68, 2), dtype=[("a", "<f4"), ("b", "<i4")])
    p = _npz(d, "out/landmarks.npz", "lm.npz", points=pts)
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'points'", "dtype"))


def c_datetime_points(d):
    pts = np.zeros((24, 68, 2), dtype="datetime64[s]")
    p = _npz(d, "out/landmarks.npz", "lm.npz", points=pts)
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'points'", "dtype"))


def c_confidence_nan(d):
    c = np.load(d / "out/landmarks.npz")["confidence"].copy()
    c[2, 5] = np.nan
    p = _npz(d, "out/landmarks.npz", "lm.npz", confidence=c)
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'confidence'", "frame 2"))


def c_confidence_above_one(d):
    c = np.load(d / "out/landmarks.npz")["confidence"].copy()
    c[4, 1] = 1.5
    p = _npz(d, "out/landmarks.npz", "lm.npz", confidence=c)
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'confidence'", "[0, 1]"))


def c_frames_wrong_length(d):
    p = _npz(d, "out/landmarks.npz", "lm.npz", frames=np.arange(5))
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'frames'"))


def c_names_wrong_length(d):
    p = _npz(d, "out/landmarks.npz", "lm.npz", names=np.array(["a", "b"]))
    return Case(["select", str(p), "-o", str(d / "out/k.json")], ("lm.npz", "'names'"))


def c_key_frames_bool(d):
    def edit(k):
        k["regions"]["mouth"]["frames"] = [True, 5]
    return Case(["decompose", str(d / "out/landmarks.npz"), str(_keys(d, edit)), "-o", str(d / "out/w.npz")],
                ("badkeys.json", "mouth", "frames"))


def c_config_not_utf8(d):
    (d / "bad.yaml").write_bytes((d / "config.yaml").read_bytes() + b"# caf\xe9\n")
    return Case(["run", str(d / "bad.yaml")], ("bad.yaml", "UTF-8"), code=2)


def c_keys_not_utf8(d):
    (d / "badkeys.json").write_bytes(b'{"regions": "\xff\xfe"}')
    return Case(["decompose", str(d / "out/landmarks.npz"), str(d / "badkeys.json"), "-o", str(d / "out/w.npz")],
                ("badkeys.json", "UTF-8"))


def c_csv_not_utf8(d):
    (d / "ann.csv").write_bytes(b"frame,point,x,y\n0,0,1,1\n0,1,\xff,2\n")
    return Case(["track", str(d / "face.mp4"), "--init", str(d / "ann.csv"), "-o", str(d / "out/lm.npz")],
                ("ann.csv", "UTF-8"))


def c_lost_fraction_nan(d):
    (d / "out/weights.npz").unlink()

    def edit(c):
        c["decompose"]["lost_fraction"] = float("nan")
    return Case(_run(d, edit), ("bad.yaml", "decompose.lost_fraction", "finite"), code=2)


def c_alpha_nan(d):
    import shutil

    shutil.rmtree(d / "out")  # so that nothing is up to date: the error must come before track runs

    def edit(c):
        c["decompose"]["alpha"] = float("nan")
    return Case(_run(d, edit), ("bad.yaml", "decompose.alpha", "finite"), code=2)


def c_output_dir_is_a_file(d):
    def edit(c):
        c["output_dir"] = "face.mp4"
    return Case(_run(d, edit), ("bad.yaml", "output_dir", "not a folder"), code=2)


def c_unexpected_exception(d, monkeypatch=None):
    # a bug (any exception type) still gives one line
    p = _npz(d, "out/landmarks.npz", "lm.npz")
    return Case(["select", str(p), "-o", str(d / "out/k.json"), "--region", "face=all", "-k", "3"],
                ("internal error", "ZeroDivisionError"))


CASES = {f.__name__[2:]: f for f in list(globals().values()) if callable(f) and getattr(f, "__name__", "")
         .startswith("c_")}


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_one_line_and_touches_nothing(name, take, monkeypatch):
    if name == "unexpected_exception":
        import retarget_cli.stages.select as sel

        monkeypatch.setattr(sel, "select_keys", lambda *a, **k: 1 / 0)
    case = CASES[name](take)
    before = snapshot(take.parent)
    res = CliRunner().invoke(main, ["-q", *map(str, case.args)])
    assert res.exit_code == case.code, (res.exit_code, res.output)
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.output
    for text in case.expect:
        assert text in lines[0], (text, lines[0])
    after = snapshot(take.parent)
    out = f"take/{case.out}/"
    changed = sorted(k for k in set(before) | set(after)
                     if before.get(k) != after.get(k) and not k.startswith(out))
    assert not changed, f"changed outside {out}: {changed}"


def test_traceback_only_with_vv(take, monkeypatch):
    import retarget_cli.stages.select as sel

    monkeypatch.setattr(sel, "select_keys", lambda *a, **k: 1 / 0)
    args = ["select", str(take / "out/landmarks.npz"), "-o", str(take / "out/k.json")]
    quiet = CliRunner().invoke(main, args)
    loud = CliRunner().invoke(main, ["-vv", *args])
    assert quiet.exit_code == loud.exit_code == 1
    assert "Traceback" not in quiet.output and "Traceback" in loud.stderr
    assert loud.stderr.strip().splitlines()[-1].startswith("error: internal error (ZeroDivisionError")


def test_set_seed_is_accepted(take):
    res = CliRunner().invoke(main, ["-q", "run", str(take / "config.yaml"), "--set", "seed=3", "--until", "select"])
    assert res.exit_code == 0, res.output
    man = json.loads((take / "out/.retarget/select.json").read_text())
    assert man["settings"]["seed"] == 3

"""apply's exports for rig users, read back by independent readers: Live Link Face CSV (csv by column name),
USD (pxr), glTF (pygltflib)."""

import csv
import logging

import numpy as np
import pytest
from click.testing import CliRunner
from usd_readback import usd_blendshape_frames

from retarget_cli.cli.commands import main
from retarget_cli.errors import InputError
from retarget_cli.io.editfiles import read_animation, write_animation
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.livelink import ARKIT_SHAPES, COLUMNS, canonical_name, parse_timecode, timecode
from retarget_cli.io.rig import load_rig, read_rig
from retarget_cli.io.stagefiles import save_weights, write_targets
from retarget_cli.stages import run_apply

T, FPS = 12, 30.0
#: Slider names spelt the ways rigs spell them; the ARKit column each maps to automatically (or None).
SLIDERS = {"jawOpen": "JawOpen", "eyeBlink_L": "EyeBlinkLeft", "EyeBlinkRight": "EyeBlinkRight",
           "mouthLeft": "MouthLeft", "mouth_smile.R": "MouthSmileRight", "browInnerUp_L": None, "browInnerUp_R": None,
           "custom": None}


def grid_obj(nx=7, ny=5):
    """A quad grid with a UV seam down the middle column and two materials; (text, vertices, faces)."""
    u, v = np.meshgrid(np.linspace(-3, 3, nx), np.linspace(-2, 2, ny))
    V = np.stack([u.ravel(), v.ravel(), 0.3 * np.cos(u.ravel())], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    uv = np.stack([(u.ravel() + 3) / 6, (v.ravel() + 2) / 4], 1)
    mid = nx // 2
    # The right half has its own UV island (shifted copies): vertices on the middle column get two UVs.
    right = np.isin(quads % nx, np.arange(mid, nx)).all(1)
    uv2 = uv + [0.05, 0.0]
    lines = ["mtllib grid.mtl"] + [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in np.concatenate([uv, uv2])]
    n = len(V)
    for mat, sel in (("left_mat", ~right), ("right_mat", right)):
        lines.append(f"usemtl {mat}")
        for q, r in zip(quads[sel], right[sel]):
            lines.append("f " + " ".join(f"{i + 1}/{i + 1 + (n if r else 0)}" for i in q))
    return "\n".join(lines) + "\n", V, quads


@pytest.fixture
def rig_scene(tmp_path):
    """A small rig (the grid and one shape per SLIDERS entry), keys posed on it, weights and landmarks."""
    rng = np.random.default_rng(3)
    text, V, _ = grid_obj()
    r = tmp_path / "rig"
    r.mkdir()
    (r / "neutral.obj").write_text(text)
    (r / "grid.mtl").write_text("newmtl left_mat\nKd 0.8 0.2 0.1\nnewmtl right_mat\nKd 0.1 0.3 0.9\n")
    shapes = {}
    for k, name in enumerate(SLIDERS):
        D = np.zeros_like(V)
        moved = rng.choice(len(V), size=6 + k, replace=False)  # sparse shapes
        D[moved] = rng.normal(size=(len(moved), 3)) * 0.3
        lines = text.splitlines()
        vi = [i for i, ln in enumerate(lines) if ln.startswith("v ")]
        for i, p in zip(vi, V + D):
            lines[i] = f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}"
        (r / f"{k}.obj").write_text("\n".join(lines) + "\n")
        shapes[name] = f"{k}.obj"
    import yaml

    (r / "rig.yaml").write_text(yaml.safe_dump({"neutral": "neutral.obj", "shapes": shapes}, sort_keys=False))
    rig = load_rig(r / "rig.yaml")
    K = 4
    frames = np.array([0, 3, 6, 9])
    S = rng.uniform(0, 1, size=(K, len(SLIDERS)))
    S[0] = 0  # the neutral key
    t = tmp_path / "t"
    t.mkdir()
    write_animation(t / "sliders.npz", rig.names, S, frames)
    keys = {}
    from retarget_cli.io.obj import write_obj

    for f, s in zip(frames, S):
        write_obj(t / f"key_{f:05d}.obj", rig.template, rig.evaluate(s))
        keys[int(f)] = f"key_{f:05d}.obj"
    write_targets(t / "targets.yaml", {"face": {"keys": keys}}, rig="../rig/rig.yaml", sliders="sliders.npz")
    W = rng.dirichlet(np.ones(K), size=T)
    save_weights(tmp_path / "weights.npz", {"face": (W, frames, np.zeros(T))}, {"fps": FPS})
    roll = 0.02 * np.arange(T)  # image-plane roll (y down), radians
    heads = np.stack([[[np.cos(a), -np.sin(a), 1.0 * i], [np.sin(a), np.cos(a), 0.0]] for i, a in enumerate(roll)])
    pts = rng.uniform(50, 150, size=(T, 68, 2))
    save_landmarks(tmp_path / "landmarks.npz", Landmarks(pts, np.ones((T, 68)), heads, pts, FPS, np.array([200, 200])))
    return tmp_path, rig, W @ S, roll


def apply_rig(tmp, out, formats, **kw):
    return run_apply(weights=tmp / "weights.npz", targets=tmp / "t" / "targets.yaml", output=out, formats=formats, **kw)


def read_livelink(path):
    """Rows of a Live Link Face CSV as {column: text}, by column name."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return rows


# --------------------------------------------------------------------------- Live Link Face CSV


def test_livelink_columns_are_the_61_values_in_live_link_face_order():
    assert COLUMNS[:2] == ("Timecode", "BlendShapeCount") and len(COLUMNS) == 2 + 61
    assert len(ARKIT_SHAPES) == 52 and len(set(COLUMNS)) == len(COLUMNS)
    # Live Link Face puts Right before Left for the jaw and mouth sideways shapes.
    assert ARKIT_SHAPES.index("JawRight") + 1 == ARKIT_SHAPES.index("JawLeft")
    assert ARKIT_SHAPES.index("MouthRight") + 1 == ARKIT_SHAPES.index("MouthLeft")
    assert ARKIT_SHAPES[0] == "EyeBlinkLeft" and ARKIT_SHAPES[-1] == "TongueOut"
    assert COLUMNS[-9:] == ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                            "RightEyeYaw", "RightEyePitch", "RightEyeRoll")


@pytest.mark.parametrize("name, arkit", [("eyeBlink_L", "EyeBlinkLeft"), ("EyeBlink.R", "EyeBlinkRight"),
                                         ("eyeblinkleft", "EyeBlinkLeft"), ("jawLeft", "JawLeft"),
                                         ("mouthSmile-Right", "MouthSmileRight"), ("JAWOPEN", "JawOpen")])
def test_slider_names_match_arkit_names_by_case_and_side(name, arkit):
    assert canonical_name(name) == canonical_name(arkit)


def test_timecodes_count_frames_within_the_second_and_parse_back():
    assert timecode(0, 30) == "00:00:00:00.000"
    assert timecode(31, 30) == "00:00:01:01.000"
    assert timecode(30 * 3661 + 7, 30) == "01:01:01:07.000"
    for fps in (24.0, 25.0, 29.97, 60.0):
        for f in (0, 1, 59, 1000, 12345):
            assert abs(parse_timecode(timecode(f, fps), fps) - f / fps) < 1e-3 / fps


def test_livelink_csv_reproduces_the_mapped_curves_by_column_name(rig_scene, caplog):
    tmp, rig, curves, roll = rig_scene
    with caplog.at_level(logging.WARNING, logger="retarget_cli"):
        apply_rig(tmp, tmp / "out", ["curves", "livelink"], landmarks=tmp / "landmarks.npz")
    rows = read_livelink(tmp / "out" / "livelink.csv")
    names, C, _, _ = read_animation(tmp / "out" / "curves.npz")
    np.testing.assert_allclose(C, curves, atol=1e-12)
    assert len(rows) == T and list(rows[0]) == list(COLUMNS)
    for t, row in enumerate(rows):
        assert row["BlendShapeCount"] == "61"
        assert abs(parse_timecode(row["Timecode"], FPS) - t / FPS) < 1e-9
    got = lambda col: np.array([float(r[col]) for r in rows])
    for slider, arkit in SLIDERS.items():
        if arkit is not None:
            np.testing.assert_allclose(got(arkit), C[:, names.index(slider)], atol=5e-7)
    # Unmapped columns are 0 and named in one warning.
    assert np.all(got("BrowInnerUp") == 0) and np.all(got("TongueOut") == 0)
    warnings = [r.getMessage() for r in caplog.records if "Live Link Face" in r.getMessage()]
    assert len(warnings) == 1 and "BrowInnerUp" in warnings[0] and "TongueOut" in warnings[0]
    assert "JawOpen" not in warnings[0] and "47 ARKit columns" in warnings[0]
    # Head roll from the tracked head motion (counter-clockwise seen by the camera); yaw and pitch are 0.
    np.testing.assert_allclose(got("HeadRoll"), -roll, atol=5e-7)
    assert np.all(got("HeadYaw") == 0) and np.all(got("HeadPitch") == 0)


def test_livelink_eye_columns_follow_the_tracked_gaze(rig_scene):
    """Eye yaw/pitch (radians, ARKit's face frame) from landmarks.npz's gaze, looking ahead at its rest median."""
    tmp, _, _, _ = rig_scene
    from retarget_cli.io.landmarks import load_landmarks
    from retarget_cli.io.livelink import EYEBALL_RADIUS

    lm = load_landmarks(tmp / "landmarks.npz")
    pts = np.tile(lm.points[:1], (T, 1, 1))  # every frame at rest
    g = np.zeros((T, 2, 2))
    g[:, :, 0] = 0.02 * (np.arange(T) - T // 2)[:, None]  # both irises sweep toward the image's right
    g[:, 1, 1] = 0.01 * (np.arange(T) - T // 2)            # the left eye (image right) looks down
    lm.points, lm.stabilized, lm.gaze, lm.gaze_valid = pts, pts, g, np.ones((T, 2), bool)
    save_landmarks(tmp / "gaze.npz", lm)
    apply_rig(tmp, tmp / "out", ["livelink"], landmarks=tmp / "gaze.npz")
    rows = read_livelink(tmp / "out" / "livelink.csv")
    got = lambda col: np.array([float(r[col]) for r in rows])
    from retarget_cli.methods.gaze_rig import rest_gaze
    from retarget_cli.methods.neutral import find_rest_frame

    rest = rest_gaze(g, None, find_rest_frame(pts).members)
    # the actor looking to their left: both eyes' yaw > 0; down: pitch > 0
    np.testing.assert_allclose(got("LeftEyeYaw"), np.arcsin((g[:, 1, 0] - rest[1, 0]) / EYEBALL_RADIUS), atol=2e-6)
    np.testing.assert_allclose(got("RightEyeYaw"), np.arcsin((g[:, 0, 0] - rest[0, 0]) / EYEBALL_RADIUS), atol=2e-6)
    np.testing.assert_allclose(got("LeftEyePitch"), np.arcsin((g[:, 1, 1] - rest[1, 1]) / EYEBALL_RADIUS),
                               atol=2e-6)
    assert np.all(np.diff(got("LeftEyeYaw")) > 0) and np.all(np.diff(got("RightEyeYaw")) > 0)
    assert np.all(np.diff(got("LeftEyePitch")) > 0) and np.all(got("RightEyePitch") == 0) and np.all(got("LeftEyeRoll") == 0)
    # without a gaze in the landmarks the eye columns are 0
    apply_rig(tmp, tmp / "none", ["livelink"], landmarks=tmp / "landmarks.npz")
    assert all(float(r["LeftEyeYaw"]) == 0 for r in read_livelink(tmp / "none" / "livelink.csv"))


def test_rig_yaml_names_map_the_remaining_columns(rig_scene):
    tmp, _, _, _ = rig_scene
    y = tmp / "rig" / "rig.yaml"
    y.write_text(y.read_text() + "names:\n  BrowInnerUp: [browInnerUp_L, browInnerUp_R]\n  tongueOut: custom\n"
                 "  JawOpen: custom\n")
    apply_rig(tmp, tmp / "out", ["curves", "livelink"])
    rows = read_livelink(tmp / "out" / "livelink.csv")
    names, C, _, _ = read_animation(tmp / "out" / "curves.npz")
    got = lambda col: np.array([float(r[col]) for r in rows])
    want = (C[:, names.index("browInnerUp_L")] + C[:, names.index("browInnerUp_R")]) / 2
    np.testing.assert_allclose(got("BrowInnerUp"), want, atol=5e-7)
    np.testing.assert_allclose(got("TongueOut"), C[:, names.index("custom")], atol=5e-7)
    np.testing.assert_allclose(got("JawOpen"), C[:, names.index("custom")], atol=5e-7)  # names: wins
    assert np.all(got("HeadRoll") == 0)  # no landmarks file


@pytest.mark.parametrize("entry, message", [("  BrowUp: custom\n", "names.BrowUp: not an ARKit blendshape"),
                                            ("  JawOpen: jaw_open\n", "names.JawOpen: unknown slider 'jaw_open'"),
                                            ("  JawOpen: []\n", "names.JawOpen: expected a slider name")])
def test_bad_names_mapping_is_a_one_line_error(rig_scene, entry, message):
    tmp, _, _, _ = rig_scene
    y = tmp / "rig" / "rig.yaml"
    y.write_text(y.read_text() + "names:\n" + entry)
    with pytest.raises(InputError, match=message):
        read_rig(y)


def test_livelink_needs_a_rig_and_is_deterministic(rig_scene):
    tmp, _, _, _ = rig_scene
    apply_rig(tmp, tmp / "a", ["livelink"], landmarks=tmp / "landmarks.npz")
    apply_rig(tmp, tmp / "b", ["livelink"], landmarks=tmp / "landmarks.npz")
    assert (tmp / "a" / "livelink.csv").read_bytes() == (tmp / "b" / "livelink.csv").read_bytes()
    r = CliRunner().invoke(main, ["apply", str(tmp / "weights.npz"), str(tmp / "t" / "targets.yaml"), "--drive",
                                  "keys", "--format", "livelink", "-o", str(tmp / "c")])
    assert r.exit_code == 1 and "format livelink needs keys posed on a rig" in r.stderr


# --------------------------------------------------------------------------- USD


def test_usd_skel_reproduces_curves_and_meshes(rig_scene):
    pytest.importorskip("pxr")
    from pxr import UsdSkel

    from retarget_cli.io.obj import read_obj

    tmp, rig, _, _ = rig_scene
    apply_rig(tmp, tmp / "out", ["obj", "curves", "usd"])
    stage, names, W, X = usd_blendshape_frames(tmp / "out" / "animation.usd")
    slider_names, C, _, _ = read_animation(tmp / "out" / "curves.npz")
    assert names == slider_names and stage.GetTimeCodesPerSecond() == FPS and len(W) == T
    np.testing.assert_allclose(W, C, atol=1e-6)
    objs = np.stack([read_obj(tmp / "out" / f"frame_{t:05d}.obj").vertices for t in range(T)])
    np.testing.assert_allclose(X, objs, atol=1e-5)
    # Sparse shapes: offsets only for the vertices they move.
    mesh = next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh")
    shape = UsdSkel.BlendShape(mesh.GetChild("jawOpen"))
    assert len(shape.GetPointIndicesAttr().Get()) == 6 == len(shape.GetOffsetsAttr().Get())
    st = mesh.GetAttribute("primvars:st")
    assert st.GetMetadata("interpolation") == "faceVarying" and len(st.Get()) == 2 * rig.n_vertices


def test_usd_bakes_correctives_as_shapes_driven_by_the_product(rig_scene):
    pytest.importorskip("pxr")
    tmp, rig, _, _ = rig_scene
    r = tmp / "rig"
    C = rig.neutral.copy()
    C[[0, 5]] += [[0.1, 0.2, -0.3], [0.0, 0.4, 0.1]]
    from retarget_cli.io.obj import write_obj

    write_obj(r / "corr.obj", rig.template, C)
    (r / "rig.yaml").write_text((r / "rig.yaml").read_text()
                                + "correctives:\n  - {shapes: [jawOpen, mouthLeft], obj: corr.obj}\n")
    apply_rig(tmp, tmp / "out", ["curves", "usd"])
    _, names, W, X = usd_blendshape_frames(tmp / "out" / "animation.usd")
    slider_names, S, _, _ = read_animation(tmp / "out" / "curves.npz")
    assert names == [*slider_names, "corrective_jawOpen_mouthLeft"]
    prod = S[:, slider_names.index("jawOpen")] * S[:, slider_names.index("mouthLeft")]
    np.testing.assert_allclose(W[:, -1], prod, atol=1e-6)
    want = rig.evaluate(S) + prod[:, None, None] * (C - rig.neutral)
    np.testing.assert_allclose(X, want, atol=1e-5)


def test_usd_point_cache_without_a_rig_and_head_motion(rig_scene):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from retarget_cli.io.obj import read_obj

    tmp, _, _, _ = rig_scene
    kw = dict(landmarks=tmp / "landmarks.npz", head_motion="2d", scale=0.05)
    apply_rig(tmp, tmp / "out", ["obj", "usd"], drive="keys", **kw)
    stage = Usd.Stage.Open(str(tmp / "out" / "animation.usd"))
    mesh = UsdGeom.Mesh(next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh"))
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetEndTimeCode() == T - 1
    assert mesh.GetPointsAttr().GetNumTimeSamples() == T
    for t in (0, 5, T - 1):
        pts = np.array(mesh.GetPointsAttr().Get(Usd.TimeCode(t)), dtype=np.float64)
        M = np.array(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(Usd.TimeCode(t)))
        world = pts @ M[:3, :3] + M[3, :3]
        np.testing.assert_allclose(world, read_obj(tmp / "out" / f"frame_{t:05d}.obj").vertices, atol=1e-4)


def test_usd_is_deterministic_and_needs_usd_core(rig_scene, monkeypatch):
    pytest.importorskip("pxr")
    import sys

    tmp, _, _, _ = rig_scene
    apply_rig(tmp, tmp / "a", ["usd"])
    apply_rig(tmp, tmp / "b", ["usd"])
    assert (tmp / "a" / "animation.usd").read_bytes() == (tmp / "b" / "animation.usd").read_bytes()
    assert sorted(p.name for p in (tmp / "a").iterdir()) == [".retarget-apply.json", "animation.usd"]  # no temporary file left
    monkeypatch.setitem(sys.modules, "pxr", None)  # as if usd-core were not installed
    r = CliRunner().invoke(main, ["apply", str(tmp / "weights.npz"), str(tmp / "t" / "targets.yaml"), "--format",
                                  "usd", "-o", str(tmp / "c")])
    assert r.exit_code == 1 and "usd-core" in r.stderr and "retarget[usd]" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp / "c").exists()


# --------------------------------------------------------------------------- glTF


def read_glb(path):
    """pygltflib's view of a glb: (gltf, accessor reader)."""
    from pygltflib import GLTF2

    g = GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a.type]
        dt = np.uint32 if a.componentType == 5125 else np.float32
        view = g.bufferViews[a.bufferView]
        data = np.frombuffer(blob, dt, count=a.count * n, offset=view.byteOffset + (a.byteOffset or 0))
        return data.reshape(a.count, n) if n > 1 else data

    return g, acc


def obj_corners(path):
    """Per face of an OBJ (read here, independently): material, [(v, vt), ...] 0-based."""
    faces, mat = [], None
    for line in path.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "usemtl":
            mat = tok[1]
        elif tok and tok[0] == "f":
            faces.append((mat, [tuple(int(x) - 1 for x in c.split("/")[:2]) for c in tok[1:]]))
    return faces


def test_glb_has_the_rig_shapes_as_named_morph_targets_uvs_normals_and_base_colours(rig_scene):
    from retarget_cli.io.obj import read_obj

    tmp, rig, _, _ = rig_scene
    apply_rig(tmp, tmp / "out", ["obj", "curves", "glb"])
    g, acc = read_glb(tmp / "out" / "animation.glb")
    mesh = g.meshes[0]
    assert mesh.extras["targetNames"] == list(rig.names)
    prims = mesh.primitives
    assert len(prims) == 2 and all(len(p.targets) == rig.n_sliders for p in prims)
    P = acc(prims[0].attributes.POSITION)
    D = np.stack([acc(t["POSITION"]) for t in prims[0].targets])
    anim = g.animations[0]
    sampler = anim.samplers[anim.channels[0].sampler]
    times = acc(sampler.input)
    W = acc(sampler.output).reshape(len(times), -1)
    _, C, _, _ = read_animation(tmp / "out" / "curves.npz")
    np.testing.assert_allclose(W, C, atol=1e-6)
    np.testing.assert_allclose(times, np.arange(T) / FPS, rtol=1e-6)
    frames = P[None] + np.einsum("tm,mnd->tnd", W, D)
    objs = np.stack([read_obj(tmp / "out" / f"frame_{t:05d}.obj").vertices for t in range(T)])
    N = rig.n_vertices
    # The seam down the middle column splits its vertices: N + one copy per seam vertex (5 rows).
    assert len(P) == N + 5
    np.testing.assert_allclose(frames[:, :N], objs, atol=1e-5)  # every frame, the OBJ's vertices in order
    uv = acc(prims[0].attributes.TEXCOORD_0)
    nrm = acc(prims[0].attributes.NORMAL)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-6)
    # Every triangle corner: its position at every frame is its OBJ vertex's, its UV the corner's vt.
    vt_lines = np.array([[float(x) for x in ln.split()[1:]] for ln in
                         (tmp / "rig" / "neutral.obj").read_text().splitlines() if ln.startswith("vt ")])
    faces = obj_corners(tmp / "rig" / "neutral.obj")
    kd = {"left_mat": [0.8, 0.2, 0.1, 1.0], "right_mat": [0.1, 0.3, 0.9, 1.0]}
    for prim in prims:
        mat = g.materials[prim.material]
        np.testing.assert_allclose(mat.pbrMetallicRoughness.baseColorFactor, kd[mat.name])
        tris = acc(prim.indices).reshape(-1, 3)
        want = [c for m, f in faces if m == mat.name for i in range(1, len(f) - 1) for c in (f[0], f[i], f[i + 1])]
        want = np.array(want)
        assert len(tris) * 3 == len(want)
        np.testing.assert_allclose(frames[:, tris.ravel()], objs[:, want[:, 0]], atol=1e-5)
        np.testing.assert_allclose(uv[tris.ravel()], vt_lines[want[:, 1]] * [1, -1] + [0, 1], atol=1e-6)
        # Smooth normals: the seam copies share their vertex's normal, and face the same way as the triangles.
        np.testing.assert_allclose(nrm[tris.ravel()], nrm[want[:, 0]], atol=1e-6)
        a, b, c = (P[tris[:, k]] for k in range(3))
        face_n = np.cross(b - a, c - a)
        assert np.all(np.einsum("td,td->t", face_n, nrm[tris[:, 0]]) > 0)

"""apply's exports read back: OBJ sequence, weights CSV, EXR texture, glb."""

import json
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io.exr import read_vat
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.obj import format_obj, read_obj
from retarget_cli.io.stagefiles import save_weights, write_targets
from retarget_cli.methods.blending import blend_keys, blend_regions, region_weights
from retarget_cli.stages import run_apply

T, FPS = 9, 24.0


def _similarity(s, theta, tx, ty):
    c, sn = s * np.cos(theta), s * np.sin(theta)
    return np.array([[c, -sn, tx], [sn, c, ty]])


@pytest.fixture
def scene(tmp_path):
    """A 12 x 10 quad character (with a pentagon) with two regions, weights and landmarks."""
    rng = np.random.default_rng(0)
    nx, ny = 12, 10
    u, v = np.meshgrid(np.linspace(-5, 5, nx), np.linspace(-4, 4, ny))
    V = np.stack([u.ravel(), v.ravel(), np.cos(u.ravel() / 4)], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    uvs = (V[:, :2] + 5) / 10
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "neutral.obj").write_bytes(
        format_obj(V, quads, uvs=uvs, face_uvs=quads, header="mtllib c.mtl\nusemtl skin\n")
        + b"f 1 2 3 4 5\n")  # an n-gon too
    V = read_obj(tmp_path / "t" / "neutral.obj").vertices  # as written (%.6f)
    regions, files = {}, {}
    for name, K, frames in (("eyes", 3, [0, 4, 7]), ("mouth", 2, [0, 5])):
        keys = {}
        for f in frames:
            rel = f"{name}/key_{f:05d}.obj"
            d = rng.normal(size=V.shape) * 0.2
            mesh = read_obj(tmp_path / "t" / "neutral.obj")
            (tmp_path / "t" / name).mkdir(exist_ok=True)
            (tmp_path / "t" / rel).write_bytes(mesh.to_bytes(V + d))
            keys[f] = rel
        mask = (V[:, 1] > 0) if name == "eyes" else (V[:, 1] <= 0)
        np.savetxt(tmp_path / "t" / f"{name}.txt", np.flatnonzero(mask), fmt="%d")
        files[name] = {"keys": keys, "vertices": f"{name}.txt", "falloff": 2.5}
        regions[name] = (rng.uniform(0, 0.7, size=(T, K)), np.array(frames), np.zeros(T))
    write_targets(tmp_path / "t" / "targets.yaml", files, neutral="neutral.obj")
    save_weights(tmp_path / "weights.npz", regions, {"fps": FPS})
    heads = np.stack([_similarity(1 + 0.02 * t, 0.03 * t, 2.0 * t, -1.0 * t) for t in range(T)])
    pts = rng.uniform(50, 150, size=(T, 68, 2))
    save_landmarks(tmp_path / "landmarks.npz",
                   Landmarks(pts, np.ones((T, 68)), heads, pts, FPS, np.array([200, 200])))
    return tmp_path, V, regions


def _expected(tmp, V, regions):
    import yaml

    spec = yaml.safe_load((tmp / "t" / "targets.yaml").read_text())["regions"]
    res, masks = [], []
    for name in sorted(regions):
        W, frames, _ = regions[name]
        B = np.stack([read_obj(tmp / "t" / spec[name]["keys"][int(f)]).vertices for f in frames])
        res.append(blend_keys(W, B))
        m = np.zeros(len(V))
        m[np.loadtxt(tmp / "t" / f"{name}.txt", dtype=int)] = 1
        masks.append(m)
    faces = read_obj(tmp / "t" / "neutral.obj").faces()
    Wt = region_weights(masks, vertices=V, faces=faces, falloff=[2.5, 2.5])
    return blend_regions(res, list(Wt[:-1]), V)


def _run(tmp, out, **kw):
    return run_apply(weights=tmp / "weights.npz", targets=tmp / "t" / "targets.yaml", output=out,
                     formats=["obj", "csv", "exr", "glb"], **kw)


def test_all_exports_read_back(scene):
    tmp, V, regions = scene
    out = tmp / "out"
    written = _run(tmp, out)
    want = _expected(tmp, V, regions)
    frames = sorted(out.glob("frame_*.obj"))
    assert len(frames) == T
    got = np.stack([read_obj(f).vertices for f in frames])
    np.testing.assert_allclose(got, want, atol=6e-7)
    # CSV: frame, time, one column per region:key.
    lines = (out / "weights.csv").read_text().splitlines()
    assert lines[0] == "frame,time,eyes:0,eyes:4,eyes:7,mouth:0,mouth:5"
    assert len(lines) == T + 1 and lines[3].startswith(f"2,{2 / FPS:.6f},")
    # EXR: one row per frame, one column per vertex, offsets from the neutral.
    vat = read_vat(out / "animation.exr")
    assert vat.shape == (T, len(V), 3) and vat.dtype == np.float32
    np.testing.assert_allclose(vat, want - V, atol=1e-5)
    side = json.loads((out / "animation.json").read_text())
    assert side["frames"] == T and side["fps"] == FPS and side["vertices"] == len(V) and side["mode"] == "offsets"
    np.testing.assert_allclose(side["bounds"]["min"], (want - V).min((0, 1)), atol=1e-5)
    np.testing.assert_allclose(side["bounds"]["max"], (want - V).max((0, 1)), atol=1e-5)
    assert {p.name for p in written} >= {"weights.csv", "animation.exr", "animation.json", "animation.glb"}


def _glb_frames(path, with_node=False):
    """Evaluate the glb at every keyed time with pygltflib (independent reader)."""
    from pygltflib import GLTF2

    g = GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        view = g.bufferViews[a.bufferView]
        n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a.type]
        dt = np.uint32 if a.componentType == 5125 else np.float32
        data = np.frombuffer(blob, dt, count=a.count * n, offset=view.byteOffset + (a.byteOffset or 0))
        return data.reshape(a.count, n) if n > 1 else data

    prim = g.meshes[0].primitives[0]
    base = acc(prim.attributes.POSITION)
    D = np.stack([acc(t["POSITION"]) for t in prim.targets])
    anim = g.animations[0]
    by_path = {c.target.path: anim.samplers[c.sampler] for c in anim.channels}
    times = acc(by_path["weights"].input)
    W = acc(by_path["weights"].output).reshape(len(times), len(D))
    pos = base[None] + np.einsum("tm,mnd->tnd", W, D)
    if with_node:
        tr = acc(by_path["translation"].output)
        q = acc(by_path["rotation"].output)
        s = acc(by_path["scale"].output)
        ang = 2 * np.arctan2(q[:, 2], q[:, 3])
        c, sn = np.cos(ang), np.sin(ang)
        R = np.zeros((len(ang), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -sn, sn, c, 1
        pos = np.einsum("tij,tnj->tni", R * s[:, :1, None], pos) + tr[:, None]
    return g, blob, times, pos


def test_glb_plays_the_same_animation_and_is_well_formed(scene):
    tmp, V, regions = scene
    out = tmp / "out"
    _run(tmp, out)
    want = _expected(tmp, V, regions)
    g, blob, times, pos = _glb_frames(out / "animation.glb")
    assert len(times) == T
    np.testing.assert_allclose(times, np.arange(T) / FPS, rtol=1e-6)
    np.testing.assert_allclose(pos, want, atol=1e-4)
    assert g.asset.version == "2.0"
    assert g.meshes[0].extras["targetNames"] == ["eyes:0", "eyes:4", "eyes:7", "eyes:rest",
                                                 "mouth:0", "mouth:5", "mouth:rest"]
    # Triangulated: 99 quads -> 198 triangles, the pentagon -> 3.
    idx = g.accessors[g.meshes[0].primitives[0].indices]
    assert idx.count == 3 * (2 * 99 + 3) and idx.componentType == 5125
    # Structure: 4-byte alignment, consistent lengths, POSITION min/max.
    data = (out / "animation.glb").read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    jlen, jtype = struct.unpack_from("<I4s", data, 12)
    blen, btype = struct.unpack_from("<I4s", data, 20 + jlen)
    assert jtype == b"JSON" and btype == b"BIN\0" and jlen % 4 == 0 and blen % 4 == 0
    assert 28 + jlen + blen == total and g.buffers[0].byteLength <= blen
    for view in g.bufferViews:
        assert view.byteOffset % 4 == 0 and view.byteOffset + view.byteLength <= g.buffers[0].byteLength
    prim = g.meshes[0].primitives[0]
    for i in [prim.attributes.POSITION] + [t["POSITION"] for t in prim.targets]:
        a = g.accessors[i]
        arr = np.frombuffer(blob, np.float32, a.count * 3, g.bufferViews[a.bufferView].byteOffset).reshape(-1, 3)
        np.testing.assert_array_equal(a.min, arr.min(0))
        np.testing.assert_array_equal(a.max, arr.max(0))


def test_head_motion_2d_moves_every_export_consistently(scene):
    tmp, V, regions = scene
    out = tmp / "out"
    _run(tmp, out, landmarks=tmp / "landmarks.npz", head_motion="2d", scale=0.1)
    objs = np.stack([read_obj(f).vertices for f in sorted(out.glob("frame_*.obj"))])
    still = _expected(tmp, V, regions)
    np.testing.assert_allclose(objs[0], still[0], atol=6e-7)  # frame 0 is the reference
    # Frame t: roll 0.03 t (image, y down) is -0.03 t about the model's z, scale 1 + 0.02 t.
    t = 5
    P = (V.min(0) + V.max(0)) / 2
    a, b = objs[t][:, :2] - objs[t][:, :2].mean(0), still[t][:, :2] - still[t][:, :2].mean(0)
    z = (a[:, 0] + 1j * a[:, 1]) / (b[:, 0] + 1j * b[:, 1])
    np.testing.assert_allclose(np.abs(z), 1 + 0.02 * t, rtol=1e-5)
    np.testing.assert_allclose(np.angle(z), -0.03 * t, atol=1e-5)
    np.testing.assert_allclose(objs[t][:, 2] - P[2], (1 + 0.02 * t) * (still[t][:, 2] - P[2]), atol=1e-5)
    _, _, _, pos = _glb_frames(out / "animation.glb", with_node=True)
    np.testing.assert_allclose(pos, objs, atol=1e-4)
    np.testing.assert_allclose(read_vat(out / "animation.exr"), objs - V, atol=1e-5)


def test_head_motion_needs_landmarks(scene):
    tmp, _, _ = scene
    with pytest.raises(Exception, match="needs the landmarks file"):
        _run(tmp, tmp / "out", head_motion="2d")


def test_exports_are_deterministic(scene):
    tmp, _, _ = scene
    _run(tmp, tmp / "a", landmarks=tmp / "landmarks.npz", head_motion="2d")
    _run(tmp, tmp / "b", landmarks=tmp / "landmarks.npz", head_motion="2d")
    names = sorted(p.name for p in (tmp / "a").iterdir())  # with apply's output manifest .retarget-apply.json
    assert names == sorted(p.name for p in (tmp / "b").iterdir()) and len(names) == T + 5
    for n in names:
        assert (tmp / "a" / n).read_bytes() == (tmp / "b" / n).read_bytes(), n


def test_cli_apply_formats_and_errors(scene):
    tmp, _, _ = scene
    args = ["apply", str(tmp / "weights.npz"), str(tmp / "t" / "targets.yaml"), "-o", str(tmp / "cli")]
    r = CliRunner().invoke(main, [*args, "--format", "csv,glb", "--head-motion", "2d",
                                  "--landmarks", str(tmp / "landmarks.npz"), "--pivot", "0,0,1"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp / "cli").iterdir()) == [".retarget-apply.json", "animation.glb", "weights.csv"]
    r = CliRunner().invoke(main, [*args, "--format", "obj,fbx"])
    assert r.exit_code == 1 and "formats" in r.stderr and "fbx" in r.stderr
    r = CliRunner().invoke(main, [*args, "--pivot", "1,2"])
    assert r.exit_code == 2 and "X,Y,Z" in r.stderr


def test_config_checks_formats_before_anything_runs(tmp_path):
    from retarget_cli.config import load_config
    from retarget_cli.errors import ConfigError
    from retarget_cli.run.pipeline import stage_params

    cfg = tmp_path / "c.yaml"
    cfg.write_text("apply: {weights: w.npz, targets: t.yaml, formats: [obj, glb]}\n")
    assert load_config(cfg, stage_params()).sections["apply"]["formats"] == ["obj", "glb"]
    for bad in ("[obj, fbx]", "[]", "[obj, obj]"):
        cfg.write_text(f"apply: {{weights: w.npz, targets: t.yaml, formats: {bad}}}\n")
        with pytest.raises(ConfigError, match="apply.formats"):
            load_config(cfg, stage_params())


def test_targets_falloff_is_validated(scene):
    from retarget_cli.errors import InputError
    from retarget_cli.io.stagefiles import read_targets

    tmp, _, _ = scene
    y = tmp / "t" / "targets.yaml"
    assert read_targets(y).regions["eyes"]["falloff"] == 2.5
    y.write_text(y.read_text().replace("falloff: 2.5", "falloff: -1", 1))
    with pytest.raises(InputError, match="falloff must be a number >= 0"):
        read_targets(y)

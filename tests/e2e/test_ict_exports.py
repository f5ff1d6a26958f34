"""The ICT FaceKit (sample_data/ict, MIT; fixture `ict_rig_dir`) exported to Live Link Face CSV, USD and glTF on
a 60-frame slice of synthetic curves (weights over key frames whose sliders are random), each read back by an
independent reader."""

import csv
import logging

import numpy as np
import pytest
from usd_readback import usd_blendshape_frames

from retarget_cli.io.editfiles import read_animation, write_animation
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.livelink import COLUMNS, parse_timecode
from retarget_cli.io.rig import load_rig
from retarget_cli.io.stagefiles import save_weights, write_targets
from retarget_cli.stages import run_apply

T, FPS = 60, 25.0


@pytest.fixture(scope="module")
def ict_exports(ict_rig_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("ict_exports")
    rng = np.random.default_rng(7)
    rig = load_rig(ict_rig_dir / "rig.yaml", cache_dir=d / "cache")
    K = 5
    frames = np.arange(K) * 10
    S = rng.uniform(0, 1, size=(K, rig.n_sliders)) * (rng.uniform(size=(K, rig.n_sliders)) < 0.3)
    S[0] = 0
    write_animation(d / "sliders.npz", rig.names, S, frames)
    keys = {int(f): f"key_{f:05d}.obj" for f in frames}  # not read when the rig drives
    write_targets(d / "targets.yaml", {"face": {"keys": keys}}, rig=str(ict_rig_dir / "rig.yaml"),
                  sliders="sliders.npz")
    save_weights(d / "weights.npz", {"face": (rng.dirichlet(np.ones(K), size=T), frames, np.zeros(T))}, {"fps": FPS})
    roll = 0.1 * np.sin(np.arange(T) / 9)
    heads = np.stack([[[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0]] for a in roll])
    pts = rng.uniform(100, 400, size=(T, 68, 2))
    save_landmarks(d / "landmarks.npz", Landmarks(pts, np.ones((T, 68)), heads, pts, FPS, np.array([512, 512])))
    return d, rig, roll


def test_ict_rig_exports_to_livelink_usd_and_glb(ict_exports, caplog):
    pytest.importorskip("pxr")
    d, rig, roll = ict_exports
    with caplog.at_level(logging.WARNING, logger="retarget_cli"):
        run_apply(weights=d / "weights.npz", targets=d / "targets.yaml", output=d / "out",
                  formats=["curves", "livelink", "usd", "glb"], landmarks=d / "landmarks.npz", cache_dir=d / "cache")
    names, C, _, _ = read_animation(d / "out" / "curves.npz")
    assert len(C) == T and C.max() > 0.2
    # Live Link Face CSV, by column name.
    with open(d / "out" / "livelink.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(COLUMNS) and len(rows) == T
    col = lambda c: np.array([float(r[c]) for r in rows])
    np.testing.assert_allclose(col("JawOpen"), C[:, names.index("jawOpen")], atol=5e-7)
    np.testing.assert_allclose(col("EyeBlinkLeft"), C[:, names.index("eyeBlink_L")], atol=5e-7)
    np.testing.assert_allclose(col("MouthRight"), C[:, names.index("mouthRight")], atol=5e-7)
    np.testing.assert_allclose(col("BrowInnerUp"), C[:, [names.index("browInnerUp_L"),
                                                           names.index("browInnerUp_R")]].mean(1), atol=5e-7)
    np.testing.assert_allclose(col("HeadRoll"), -roll, atol=5e-7)
    assert [abs(parse_timecode(r["Timecode"], FPS) - t / FPS) < 1e-9 for t, r in enumerate(rows)] == [True] * T
    warned = [r.getMessage() for r in caplog.records if "Live Link Face" in r.getMessage()]
    assert len(warned) == 1 and "1 ARKit columns" in warned[0] and "TongueOut" in warned[0]
    # USD: UsdSkel's own evaluation.
    stage, usd_names, W, X = usd_blendshape_frames(d / "out" / "animation.usd")
    assert usd_names == names and stage.GetTimeCodesPerSecond() == FPS
    np.testing.assert_allclose(W, C, atol=1e-6)
    np.testing.assert_allclose(X, rig.evaluate(C), atol=1e-5)  # the OBJ frames (tests/e2e/test_real_rig.py)
    # glTF: the rig's named shapes, every frame, UVs and normals.
    from pygltflib import GLTF2

    g = GLTF2().load_binary(str(d / "out" / "animation.glb"))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a.type]
        data = np.frombuffer(blob, np.float32, a.count * n, g.bufferViews[a.bufferView].byteOffset)
        return data.reshape(a.count, n) if n > 1 else data

    prim = g.meshes[0].primitives[0]
    assert g.meshes[0].extras["targetNames"] == names
    assert len(g.meshes[0].primitives) == len(g.materials) >= 10  # one per usemtl material
    P = acc(prim.attributes.POSITION)
    D = np.stack([acc(t["POSITION"]) for t in prim.targets])
    sampler = g.animations[0].samplers[0]
    Wg = acc(sampler.output).reshape(T, -1)
    np.testing.assert_allclose(Wg, C, atol=1e-6)
    N = rig.n_vertices
    assert len(P) > N  # split at UV seams
    got = P[None, :N] + np.einsum("tm,mnd->tnd", Wg, D[:, :N])
    np.testing.assert_allclose(got, rig.evaluate(C), atol=1e-4)
    uv, nrm = acc(prim.attributes.TEXCOORD_0), acc(prim.attributes.NORMAL)
    vt = np.array([[float(x) for x in ln.split()[1:3]] for ln in
                   (rig.template.path).read_text().splitlines() if ln.startswith("vt ")])
    # One glTF vertex per distinct (vertex, vt) corner: every vt of the OBJ (its UDIM tiles too), v flipped.
    flipped = uv * [1, -1] + [0, 1]
    from scipy.spatial import cKDTree

    assert cKDTree(vt).query(flipped)[0].max() < 1e-5 and cKDTree(flipped).query(vt)[0].max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1, atol=1e-5)

"""A take with gaps end to end (issue 33): select never keys a gap frame, each segment is posed apart, and the
rig's curves in the gaps follow apply.gaps (ease, hold, omit) in curves.csv/.npz and livelink.csv.

The actor is the synthetic landmark rig (retarget_cli.synth.take.landmark_rig) seen through a camera, as in
test_rest_pose.py; frames 60-99 are a gap (the face not found: the last found frame's landmarks held with
confidence 0, as track writes them) and a scene cut starts a new segment at frame 130.
"""

import importlib.util
import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from retarget_cli.cli.commands import main
from retarget_cli.io.landmarks import Landmarks, save_landmarks
from retarget_cli.io.obj import format_obj
from retarget_cli.io.rig import load_rig
from retarget_cli.methods.gaps import describe_gaps, fill_gaps, segment_ids
from retarget_cli.synth.take import EXPRESSIONS, expression_curves, landmark_rig

T = 160
GAP = slice(60, 100)
CUT = 130


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    d = tmp_path_factory.mktemp("gaps")
    L = landmark_rig(seed=1)
    (d / "shapes").mkdir()
    (d / "neutral.obj").write_bytes(format_obj(L["vertices"], L["faces"]))
    shapes = {}
    for name, delta in zip(L["names"], L["deltas"]):
        (d / "shapes" / f"{name}.obj").write_bytes(format_obj(L["vertices"] + delta, L["faces"]))
        shapes[name] = f"shapes/{name}.obj"
    (d / "rig.yaml").write_text(yaml.safe_dump({"neutral": "neutral.obj", "shapes": shapes, "range": [0, 1],
                                                "landmarks": [int(v) for v in L["landmark_vertices"]]}, sort_keys=False))
    curves = expression_curves(T, seed=3)
    rig = load_rig(d / "rig.yaml")
    R = Rotation.from_euler("xyz", [180 - 5, 8, 3], degrees=True).as_matrix()
    pts = np.stack([140 * (rig.evaluate(c)[L["landmark_vertices"]] @ R.T)[:, :2] + [150, 160] for c in curves])
    pts += 0.3 * np.random.default_rng(0).standard_normal(pts.shape)
    found = np.ones(T, bool)
    found[GAP] = False
    pts[GAP] = pts[GAP.start - 1]  # a gap holds the last found frame's landmarks, confidence 0
    conf = np.where(found[:, None], 1.0, 0.0) * np.ones((T, 68))
    cuts = np.zeros(T, bool)
    cuts[CUT] = True
    head = np.tile(np.eye(2, 3), (T, 1, 1))
    meta = {"gaps": describe_gaps(found, cuts=cuts, fps=30.0)}
    save_landmarks(d / "landmarks.npz", Landmarks(pts, conf, head, pts, 30.0, np.array([320, 320]), meta=meta,
                                                  found=found, segment=segment_ids(found, cuts)))
    formats = ["curves", "livelink", "glb"] + (["usd"] if importlib.util.find_spec("pxr") else [])
    cfg = {"output_dir": "out",
           "select": {"landmarks": "landmarks.npz", "k": 8, "regions": {"brows-eyes": None, "mouth": None}},
           "decompose": {"landmarks": "landmarks.npz", "formulation": "delta"},
           "auto_pose": {"landmarks": "landmarks.npz", "rig": "rig.yaml"},
           "apply": {"landmarks": "landmarks.npz", "formats": formats}}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    return d


def curves_npz(d):
    data = np.load(d / "out" / "frames" / "curves.npz")
    return data["curves"], data["found"], [str(n) for n in data["names"]]


def glb_key_times(path):
    """The times of the glTF's weight animation (its first sampler's input accessor)."""
    import struct

    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n])
    acc = doc["accessors"][doc["animations"][0]["samplers"][0]["input"]]
    view = doc["bufferViews"][acc["bufferView"]]
    binary = data[20 + n + 8:]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.frombuffer(binary, np.float32, count=acc["count"], offset=start)


def usd_times(path):
    """The time codes of the USD's blend-shape weights (None without the usd extra: the file is not written)."""
    if not path.is_file():
        return None
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/Character/Skel/Anim").GetAttribute("blendShapeWeights")
    return [int(t) for t in attr.GetTimeSamples()]


def csv_rows(path):
    lines = path.read_text().strip().splitlines()
    return lines[0].split(","), [ln.split(",") for ln in lines[1:]]


@pytest.fixture(scope="module")
def ran(take):
    res = run("run", take / "config.yaml")
    assert res.exit_code == 0, res.output
    return take


def test_no_key_frame_in_a_gap(ran):
    keys = json.loads((ran / "out" / "keys.json").read_text())
    for name, region in keys["regions"].items():
        inside = [f for f in region["frames"] if GAP.start <= f < GAP.stop]
        assert not inside, (name, inside)
    assert not GAP.start <= keys["neutral"]["frame"] < GAP.stop


def test_gap_frames_ease_to_rest_and_back_by_default(ran):
    C, found, names = curves_npz(ran)
    assert C.shape == (T, len(EXPRESSIONS)) and np.isfinite(C).all()
    assert found.tolist() == [not (GAP.start <= t < GAP.stop) for t in range(T)]
    n = 12  # gap_ease 0.4 s at 30 fps
    assert np.abs(C[GAP.start + n:GAP.stop - n]).max() == 0.0  # at rest between the eases
    # eased: each slider moves monotonically from the last found pose to rest, then to the next found pose
    down, up = C[GAP.start - 1:GAP.start + n + 1], C[GAP.stop - n - 1:GAP.stop + 1]
    assert np.all(np.diff(np.abs(down), axis=0) <= 1e-12) and np.all(np.diff(np.abs(up), axis=0) >= -1e-12)
    # exactly the declared fill of the found frames' curves (methods.gaps.fill_gaps, tested on its own)
    assert np.allclose(C, fill_gaps(C, found, behaviour="ease", ease_frames=n), atol=1e-6)
    assert np.abs(C[GAP.stop]).max() > 0.05  # the pose after the gap is not at rest
    header, rows = csv_rows(ran / "out" / "frames" / "curves.csv")
    assert header[:3] == ["frame", "time", "found"] and len(rows) == T
    assert [r[2] for r in rows] == ["0" if GAP.start <= t < GAP.stop else "1" for t in range(T)]
    ll_header, ll_rows = csv_rows(ran / "out" / "frames" / "livelink.csv")
    assert len(ll_rows) == T


def test_each_segment_is_posed_apart(ran):
    # the targets' curves hold the gap (auto_pose) and the take's two sides of the cut are fitted apart:
    # frame CUT's pose depends on frames from CUT on only, so refitting the segment alone gives the same
    from retarget_cli.io.editfiles import read_animation

    names, W, frames, _ = read_animation(ran / "out" / "targets" / "curves.csv")
    assert np.array_equal(frames, np.arange(T))
    assert np.all(W[GAP] == W[GAP.start - 1])  # held in the targets: apply decides
    lm = np.load(ran / "landmarks.npz")
    assert lm["segment"][CUT - 1] == 1 and lm["segment"][CUT] == 2


@pytest.mark.parametrize("behaviour", ["hold", "omit"])
def test_gap_frames_hold_or_are_left_out(ran, behaviour):
    res = run("run", ran / "config.yaml", "--set", f"apply.gaps={behaviour}")
    assert res.exit_code == 0, res.output
    C, found, _ = curves_npz(ran)
    assert C.shape[0] == T and np.all(C[GAP] == C[GAP.start - 1])  # every row, the last pose held
    header, rows = csv_rows(ran / "out" / "frames" / "curves.csv")
    _, ll_rows = csv_rows(ran / "out" / "frames" / "livelink.csv")
    frames = [int(r[0]) for r in rows]
    keyed = glb_key_times(ran / "out" / "frames" / "animation.glb")
    usd = usd_times(ran / "out" / "frames" / "animation.usd")
    if behaviour == "hold":
        assert frames == list(range(T)) and len(ll_rows) == T
        assert np.allclose(keyed, np.arange(T) / 30.0)
        assert usd is None or usd == list(range(T))
    else:
        assert np.allclose(keyed, np.array(frames) / 30.0)  # the glTF keys the found frames only
        assert usd is None or usd == frames  # and so does the USD
        assert frames == [t for t in range(T) if not GAP.start <= t < GAP.stop]
        assert len(ll_rows) == T - (GAP.stop - GAP.start)
        # each Live Link row keeps its own frame's timecode: the first after the gap is frame 100 (3 s 10 f)
        assert ll_rows[GAP.start][0].startswith("00:00:03:10")


def test_too_few_found_frames_for_the_keys_is_one_line(ran):
    res = run("-q", "select", ran / "landmarks.npz", "-o", ran / "k.json", "-k", 130)
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "found in 120 of 160 frames" in lines[0] and "k = 130" in lines[0], res.output


def test_the_report_shows_the_gaps(ran):
    pytest.importorskip("matplotlib")
    res = run("-q", "report", ran / "config.yaml", "-o", ran / "out" / "report.html")
    assert res.exit_code == 0, res.output
    page = (ran / "out" / "report.html").read_text()
    assert "2 gaps (cut 1, no face 1), 40 frames" in page
    assert "40 of 160 frames without a face" in page
    # the table: where, how long, why
    row = ('<tr><td class="num">60</td><td class="num">40</td><td class="num">1.33</td><td>no face</td><td></td></tr>'
           '<tr><td class="num">130</td><td class="num">0</td><td class="num">0.00</td><td>cut</td><td>yes</td></tr>')
    assert row in page

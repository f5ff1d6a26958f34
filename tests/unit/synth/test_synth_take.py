"""Synthetic take generator: determinism, ground-truth consistency, renderer sanity."""

import hashlib
import itertools

import cv2
import numpy as np
import pytest
import yaml

from retarget_cli.io.annotations import read_pts
from retarget_cli.io.atomic import load_npz
from retarget_cli.io.landmarks import load_landmarks
from retarget_cli.io.obj import check_same_topology, read_obj
from retarget_cli.methods.tracking.head import RIGID_68, estimate_head
from retarget_cli.synth import take as synth
from retarget_cli.synth.take import (
    EXPRESSIONS,
    expression_curves,
    head_motion,
    place_neutral,
    render_frames,
    source_deltas,
    source_neutral,
    target_animation,
    target_rig,
    write_take,
)

E = {name: i for i, name in enumerate(EXPRESSIONS)}


def landmarks_for(curves, size, head=None):
    """Image landmarks (T, 68, 2) for activation rows *curves* (T, E) and optional head (T, 2, 3)."""
    curves = np.atleast_2d(np.asarray(curves, float))
    norm = source_neutral()[None] + np.einsum("te,eld->tld", curves, source_deltas())
    P = place_neutral(size)
    pts = norm @ P[:, :2].T + P[:, 2]
    if head is not None:
        pts = np.einsum("tij,tlj->tli", head[:, :, :2], pts) + head[:, None, :, 2]
    return pts


# ---- curves ------------------------------------------------------------------


def test_curves_are_deterministic_and_depend_on_the_seed():
    a = expression_curves(150, seed=4)
    b = expression_curves(150, seed=4)
    c = expression_curves(150, seed=5)
    assert a.shape == (150, len(EXPRESSIONS)) and a.dtype == np.float64
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("fps", [24.0, 30.0, 60.0])
def test_curves_start_neutral_and_stay_in_range(fps):
    c = expression_curves(300, fps=fps, seed=1)
    assert np.all(c[0] == 0)
    assert np.all(c[np.arange(300) / fps < 0.3] == 0)
    assert c.min() >= 0 and c.max() <= 1


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("fps", [24.0, 30.0, 60.0])
def test_every_expression_reaches_0_6_in_120_frames(seed, fps):
    c = expression_curves(120, fps=fps, seed=seed)
    assert np.all(c.max(axis=0) >= 0.6), dict(zip(EXPRESSIONS, c.max(axis=0).round(2)))


def test_expressions_overlap_and_rest():
    c = expression_curves(900, seed=0)
    active = c > 0.05
    assert (active.sum(1) >= 2).any(), "no combinations of expressions"
    assert (active.sum(1) == 0)[30:].any(), "no rests"


def test_curves_are_smooth_when_not_compressed():
    c = expression_curves(900, seed=2)  # 30 s: no time compression
    slow = [i for n, i in E.items() if not n.startswith("blink")]
    assert np.abs(np.diff(c[:, slow], axis=0)).max() < 0.35
    # blinks are short: 0.15-0.3 s above zero
    on = np.flatnonzero(np.diff((c[:, E["blink_r"]] > 0).astype(int)) == 1)
    off = np.flatnonzero(np.diff((c[:, E["blink_r"]] > 0).astype(int)) == -1)
    lengths = (off[: len(on)] - on[: len(off)]) / 30.0
    assert len(lengths) >= 3 and lengths.max() <= 0.35


@pytest.mark.parametrize("kwargs", [{"n_frames": 1}, {"n_frames": 10, "fps": 0}, {"n_frames": 10, "seed": -1},
                                    {"n_frames": 2.5}])
def test_curves_reject_bad_arguments(kwargs):
    n = kwargs.pop("n_frames")
    with pytest.raises(ValueError):
        expression_curves(n, **kwargs)


# ---- source face -------------------------------------------------------------


def test_neutral_face_layout():
    n = source_neutral()
    assert n.shape == (68, 2)
    assert n[16, 0] - n[0, 0] == pytest.approx(1.0)
    np.testing.assert_allclose((n.min(0) + n.max(0)) / 2, 0, atol=1e-12)
    assert n[8, 1] > n[57, 1] > n[51, 1] > n[33, 1] > n[30, 1] > n[27, 1] > n[19, 1]  # y down
    assert n[36, 0] < n[39, 0] < n[42, 0] < n[45, 0]  # subject's right eye is image left
    gap = n[[67, 66, 65], 1] - n[[61, 62, 63], 1]
    assert np.all((gap >= 0) & (gap <= 0.01))  # closed lips


def test_deltas_keep_rigid_points_fixed_and_are_independent():
    d = source_deltas()
    assert d.shape == (len(EXPRESSIONS), 68, 2)
    assert np.all(d[:, list(RIGID_68)] == 0)
    assert np.linalg.matrix_rank(d.reshape(len(EXPRESSIONS), -1), tol=1e-6) == len(EXPRESSIONS)
    n = source_neutral()
    for name, (up, low) in (("blink_r", ([37, 38], [41, 40])), ("blink_l", ([43, 44], [47, 46]))):
        closed = n + d[E[name]]
        assert np.all(np.abs(closed[low, 1] - closed[up, 1]) < 0.005)
    assert 0.15 <= d[E["jaw_open"], 8, 1] <= 0.25
    assert d[E["brow_raise"], 17:27, 1].max() < 0 and np.all(d[E["brow_l"], 17:22] == 0)
    assert d[E["smile"], 48, 0] < 0 < d[E["smile"], 54, 0] and d[E["smile"], [48, 54], 1].max() < 0
    assert d[E["pucker"], 48, 0] > 0 > d[E["pucker"], 54, 0]
    assert np.all(d[E["smirk_l"], 48] == 0) and d[E["smirk_l"], 54, 1] < 0


def test_warp_triangulation_never_folds():
    pts, tri = synth._warp_mesh()
    d = source_deltas()

    def areas(p):
        a, b, c = p[:, tri[:, 0]], p[:, tri[:, 1]], p[:, tri[:, 2]]
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])

    rng = np.random.default_rng(0)
    corners = np.array(list(itertools.product([0.0, 1.0], repeat=len(EXPRESSIONS))))
    acts = np.concatenate([corners, rng.random((3000, len(EXPRESSIONS)))])
    p = np.repeat(pts[None], len(acts), axis=0)
    p[:, :68] += np.einsum("ne,eld->nld", acts, d)
    ratio = areas(p) / areas(pts[None])
    assert areas(pts[None]).min() > 0
    assert ratio.min() > 0.01, f"triangle {tri[np.argmin(ratio.min(0))]} folds"


# ---- head motion ---------------------------------------------------------------


def test_head_motion_identity_at_frame_0_and_bounded():
    size = (320, 240)
    head = head_motion(600, size=size, seed=3)
    assert head.shape == (600, 2, 3) and head.dtype == np.float64
    assert np.array_equal(head[0], np.eye(2, 3))
    a, b = head[:, 0, 0], head[:, 1, 0]
    np.testing.assert_allclose(head[:, 1, 1], a)
    np.testing.assert_allclose(head[:, 0, 1], -b)
    assert np.abs(np.degrees(np.arctan2(b, a))).max() <= 15 + 1e-9
    assert np.abs(np.hypot(a, b) - 1).max() <= 0.1 + 1e-9
    c = place_neutral(size)[:, 2]
    moved = np.einsum("tij,j->ti", head[:, :, :2], c) + head[:, :, 2] - c
    assert np.all(np.abs(moved) <= 0.06 * np.array(size) + 1e-9)
    assert np.abs(np.diff(head, axis=0)).max() < 0.05 * max(size)  # smooth
    assert np.array_equal(head, head_motion(600, size=size, seed=3))


def test_estimate_head_recovers_the_true_head():
    curves, stab, head, points = synth._truth_landmarks(120, (320, 320), 0, 30.0)
    got, got_stab = estimate_head(points)
    np.testing.assert_allclose(got, head, atol=1e-6)
    np.testing.assert_allclose(got_stab, stab, atol=1e-6)


@pytest.mark.parametrize("seed,size", [(0, (320, 320)), (1, (160, 160)), (2, (320, 240)), (7, (240, 320))])
def test_landmarks_stay_inside_the_image(seed, size):
    pts = synth._truth_landmarks(120, size, seed, 30.0)[3]
    assert pts[..., 0].min() >= 0 and pts[..., 0].max() <= size[0] - 1
    assert pts[..., 1].min() >= 0 and pts[..., 1].max() <= size[1] - 1


# ---- renderer ------------------------------------------------------------------


@pytest.fixture(scope="module")
def take40():
    size = (160, 160)
    pts = synth._truth_landmarks(40, size, 0, 30.0)[3]
    return size, pts, list(render_frames(pts, size=size, seed=0))


def test_render_shape_dtype_and_determinism(take40):
    size, pts, frames = take40
    assert len(frames) == 40
    assert all(f.shape == (160, 160, 3) and f.dtype == np.uint8 for f in frames)
    again = list(render_frames(pts[:5], size=size, seed=0))
    assert all(np.array_equal(a, b) for a, b in zip(again, frames[:5]))
    other = next(render_frames(pts[:1], size=size, seed=1))
    assert np.abs(other.astype(int) - frames[0]).mean() > 5


def test_rendered_skin_is_textured(take40):
    size, pts, frames = take40
    gray = cv2.cvtColor(frames[0], cv2.COLOR_BGR2GRAY).astype(float)
    highpass = gray - cv2.GaussianBlur(gray, (0, 0), 3)
    k = place_neutral(size)[0, 0]
    p = pts[0]
    centres = {"right cheek": (p[3] + p[31]) / 2, "left cheek": (p[13] + p[35]) / 2,
               "chin": (p[8] + p[57]) / 2, "forehead": (p[19] + p[24]) / 2 - [0, 0.08 * k]}
    r = max(3, int(0.05 * k))
    for where, c in centres.items():
        x, y = np.round(c).astype(int)
        patch = highpass[y - r:y + r + 1, x - r:x + r + 1]
        # sensor noise alone gives ~1.9
        assert patch.std() > 3.0, f"flat skin on the {where}: high-pass std {patch.std():.2f}"


def test_mouth_interior_is_dark_when_the_jaw_opens():
    size = (160, 160)
    c = np.zeros((2, len(EXPRESSIONS)))
    c[1, E["jaw_open"]] = 1.0
    pts = landmarks_for(c, size)
    neutral, open_ = render_frames(pts, size=size, seed=0)
    # lower half of the opening (the upper teeth show near the upper lip)
    m = np.zeros(size[::-1], np.uint8)
    x0, x1 = np.round(pts[1, 62, 0] + np.array([-0.2, 0.2]) * np.ptp(pts[1, 60:68, 0])).astype(int)
    y0, y1 = int(np.ceil(pts[1, 60:68, 1].mean())), int(np.floor(pts[1, 66, 1])) - 1
    m[y0:y1 + 1, x0:x1 + 1] = 1
    gray_open = cv2.cvtColor(open_, cv2.COLOR_BGR2GRAY)[m > 0]
    gray_neutral = cv2.cvtColor(neutral, cv2.COLOR_BGR2GRAY)[m > 0]
    assert m.sum() > 10
    assert gray_open.mean() < 60 and gray_neutral.mean() > gray_open.mean() + 40


def test_pupils_disappear_in_a_blink():
    size = (320, 320)
    c = np.zeros((2, len(EXPRESSIONS)))
    c[1, [E["blink_l"], E["blink_r"]]] = 1.0
    pts = landmarks_for(c, size)
    opened, closed = render_frames(pts, size=size, seed=0)
    for eye in (slice(36, 42), slice(42, 48)):
        x, y = np.round(pts[0, eye][[0, 3]].mean(0)).astype(int)
        dark_open = cv2.cvtColor(opened, cv2.COLOR_BGR2GRAY)[y - 1:y + 2, x - 1:x + 2].mean()
        dark_closed = cv2.cvtColor(closed, cv2.COLOR_BGR2GRAY)[y + 2:y + 5, x - 1:x + 2].mean()
        assert dark_open < 60 < dark_closed


def test_render_rejects_bad_points():
    with pytest.raises(ValueError):
        next(render_frames(np.zeros((3, 5, 2)), size=(160, 160)))
    with pytest.raises(ValueError):
        next(render_frames(np.zeros((3, 68, 2)), size=(10, 160)))


# ---- target character ----------------------------------------------------------


def test_target_rig_shape_and_expressions():
    rig = target_rig(seed=0)
    V, F, UV, D = rig["vertices"], rig["faces"], rig["uvs"], rig["deltas"]
    N = len(V)
    assert 2000 <= N <= 5000 and V.shape == (N, 3) and UV.shape == (N, 2)
    assert F.shape[1] == 4 and F.min() == 0 and F.max() == N - 1
    assert UV.min() >= 0 and UV.max() <= 1
    assert D.shape == (len(EXPRESSIONS), N, 3)
    width = np.ptp(V[:, 0])
    peak = np.linalg.norm(D, axis=2).max(axis=1) / width
    assert np.all((peak >= 0.05) & (peak <= 0.15)), dict(zip(EXPRESSIONS, peak.round(3)))
    assert np.linalg.matrix_rank(D.reshape(len(EXPRESSIONS), -1), tol=1e-6) == len(EXPRESSIONS)
    # left-side expressions move the subject's left (+x) side only
    for name in ("blink_l", "brow_l", "smirk_l"):
        moved = np.linalg.norm(D[E[name]], axis=1) > 1e-9
        assert V[moved, 0].min() > 0
    assert np.array_equal(target_rig(seed=0)["deltas"], D)


def test_target_animation_is_the_blendshape_model():
    rig = target_rig()
    c = expression_curves(20, seed=0)
    anim = target_animation(rig, c)
    assert anim.shape == (20, len(rig["vertices"]), 3)
    t = 13
    expected = rig["vertices"] + sum(c[t, e] * rig["deltas"][e] for e in range(len(EXPRESSIONS)))
    np.testing.assert_allclose(anim[t], expected, atol=1e-12)
    with pytest.raises(ValueError):
        target_animation(rig, np.zeros((5, 3)))


# ---- write_take ----------------------------------------------------------------


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    a = tmp_path_factory.mktemp("a")
    b = tmp_path_factory.mktemp("b")
    pa = write_take(a, n_frames=40, size=(160, 160), seed=5)
    pb = write_take(b, n_frames=40, size=(160, 160), seed=5)
    return a, b, pa, pb


def test_write_take_files(takes):
    a, _, paths, _ = takes
    names = {"face.mp4", "face_00000.pts", "truth_landmarks.npz", "truth.npz", "rig.yaml",
             "target/neutral.obj", "target/character.mtl", "config.yaml",
             "target/regions/brows-eyes.txt", "target/regions/mouth.txt"} | {f"target/shapes/{n}.obj" for n in EXPRESSIONS}
    got = {p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()}
    assert got == names
    assert {p.relative_to(a).as_posix() for p in paths.values()} == names

    cap = cv2.VideoCapture(str(a / "face.mp4"))
    n, ok = 0, True
    while ok:
        ok, frame = cap.read()
        if ok:
            assert frame.shape == (160, 160, 3)
            n += 1
    assert n == 40

    lm = load_landmarks(a / "truth_landmarks.npz")
    assert lm.points.shape == (40, 68, 2) and lm.fps == 30.0 and list(lm.frame_size) == [160, 160]
    assert np.all(lm.confidence == 1) and np.array_equal(lm.head[0], np.eye(2, 3, dtype=np.float32))
    assert lm.meta["source"] == "retarget synth" and lm.meta["seed"] == 5 and lm.meta["frames"] == 40
    np.testing.assert_allclose(read_pts(a / "face_00000.pts"), lm.points[0], atol=1e-3)

    truth = load_npz(a / "truth.npz")
    assert truth["curves"].shape == (40, len(EXPRESSIONS)) and truth["curves"].dtype == np.float64
    assert list(truth["names"]) == list(EXPRESSIONS)
    assert truth["target"].dtype == np.float32

    rig = yaml.safe_load((a / "rig.yaml").read_text())
    assert rig["range"] == [0, 1] and list(rig["shapes"]) == list(EXPRESSIONS)
    meshes = [read_obj(a / rig["neutral"])] + [read_obj(a / p) for p in rig["shapes"].values()]
    check_same_topology(meshes)
    assert 2000 <= meshes[0].n_vertices <= 5000
    assert truth["target"].shape == (40, meshes[0].n_vertices, 3)
    np.testing.assert_allclose(truth["target"][0], meshes[0].vertices, atol=1e-5)
    text = (a / "target" / "neutral.obj").read_text()
    assert text.startswith("# retarget synth target character\nmtllib character.mtl\no character\nusemtl skin\n")
    assert "\nvt " in text and "\nf 1/1 2/2 " in text
    for name, m in zip(EXPRESSIONS, meshes[1:]):  # full meshes at activation 1
        d = np.linalg.norm(m.vertices - meshes[0].vertices, axis=1)
        assert d.max() > 0.3, name


def test_write_take_is_byte_identical_for_the_same_seed(takes):
    a, b, pa, pb = takes
    assert {k: sha(p) for k, p in pa.items()} == {k: sha(p) for k, p in pb.items()}
    assert not list(a.glob(".*")), "temporary files left behind"


def test_region_masks_partition_the_moving_vertices():
    from retarget_cli.synth.take import REGION_EXPRESSIONS, target_region_masks

    rig = target_rig()
    masks = target_region_masks(rig)
    total = sum(masks.values())
    covered = total > 0
    np.testing.assert_allclose(total[covered], 1.0)
    # Vertices no mask covers barely move (they keep the neutral in apply).
    motion = np.linalg.norm(rig["deltas"], axis=2).sum(0)
    assert covered.mean() > 0.3 and motion[~covered].max() < 1e-3 * motion.max()
    # Each region's mask is ~1 where only its own expressions move the face.
    for region, exprs in REGION_EXPRESSIONS.items():
        own = sum(np.linalg.norm(rig["deltas"][EXPRESSIONS.index(e)], axis=1) for e in exprs)
        other = np.linalg.norm(rig["deltas"], axis=2).sum(0) - own
        only = (own > 1e-3) & (other < 1e-9)
        assert only.any() and np.allclose(masks[region][only], 1.0)

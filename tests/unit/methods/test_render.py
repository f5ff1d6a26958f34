import numpy as np
import pytest

from retarget_cli.errors import ShapeError
from retarget_cli.methods.render import Camera, Light, MeshRenderer, View, rasterize, triangulate, vertex_normals


def test_known_triangle_covers_exactly_the_pixel_centres_inside():
    # Vertices off the pixel grid: no pixel centre lies on an edge.
    xy = np.array([[0.5, 0.5], [10.7, 0.5], [0.5, 10.7]])
    tri_id, bary = rasterize(xy, np.zeros(3), np.array([[0, 1, 2]]), (16, 16))
    yy, xx = np.mgrid[0:16, 0:16]
    expected = (xx >= 1) & (yy >= 1) & (xx + yy <= 11)
    assert expected.sum() == 55
    np.testing.assert_array_equal(tri_id >= 0, expected)
    # barycentric coordinates reproduce the pixel centre
    recon = np.einsum("hwk,kd->hwd", bary, xy)
    np.testing.assert_allclose(recon[expected], np.stack([xx, yy], -1)[expected], atol=1e-5)
    assert np.all(bary[~expected] == 0)


def test_winding_does_not_matter():
    xy = np.array([[0.5, 0.5], [10.7, 0.5], [0.5, 10.7]])
    a, _ = rasterize(xy, np.zeros(3), np.array([[0, 1, 2]]), (16, 16))
    b, _ = rasterize(xy, np.zeros(3), np.array([[0, 2, 1]]), (16, 16))
    np.testing.assert_array_equal(a >= 0, b >= 0)


def test_known_quad_covers_its_rectangle_once_with_the_top_left_rule():
    # Corners on pixel centres: the left and top edges are in, the right and bottom edges out,
    # and the diagonal shared by the two triangles belongs to exactly one of them.
    xy = np.array([[10, 10], [30, 10], [30, 20], [10, 20]], dtype=float)
    tris = triangulate([[0, 1, 2, 3]])
    np.testing.assert_array_equal(tris, [[0, 1, 2], [0, 2, 3]])
    tri_id, _ = rasterize(xy, np.zeros(4), tris, (40, 30))
    yy, xx = np.mgrid[0:30, 0:40]
    rect = (xx >= 10) & (xx < 30) & (yy >= 10) & (yy < 20)
    np.testing.assert_array_equal(tri_id >= 0, rect)
    assert rect.sum() == 200
    # pixels strictly above the diagonal y = 10 + (x - 10) / 2 belong to the first triangle
    above = rect & (2 * (yy - 10) < (xx - 10))
    below = rect & (2 * (yy - 10) > (xx - 10))
    assert np.all(tri_id[above] == 0) and np.all(tri_id[below] == 1)


def test_shared_edges_leave_no_cracks_with_irregular_vertices():
    rng = np.random.default_rng(0)
    n = 9
    g = np.linspace(-2, 66, n)
    X, Y = np.meshgrid(g, g)
    xy = np.stack([X, Y], -1).reshape(-1, 2)
    inner = (X > -2) & (X < 66) & (Y > -2) & (Y < 66)
    xy[inner.ravel()] += rng.uniform(-3, 3, (inner.sum(), 2))
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    tri_id, _ = rasterize(xy, np.zeros(len(xy)), triangulate(quads), (64, 64))
    assert np.all(tri_id >= 0)  # the mesh covers the whole image: every pixel has a triangle


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_nearer_triangle_wins_whatever_the_draw_order(order):
    big = [[2.3, 2.3], [28.7, 2.3], [2.3, 28.7]]
    xy = np.array(big + big, dtype=float)
    depth = np.array([5.0, 5.0, 5.0, 1.0, 1.0, 1.0])  # second copy is nearer
    tris = np.array([[0, 1, 2], [3, 4, 5]])[list(order)]
    tri_id, _ = rasterize(xy, depth, tris, (32, 32))
    near = order.index(1)
    covered = tri_id >= 0
    assert covered.sum() > 200
    assert np.all(tri_id[covered] == near)


def test_interpenetrating_triangles_split_where_depths_cross():
    # A: depth 0 at x=0 rising to 2 at x=40; B: depth 1 everywhere. A is in front for x < 20.
    xy = np.array([[0, -1], [40, -1], [0, 41], [40, 41], [0.5, -1], [40.5, -1], [0.5, 41], [40.5, 41]], float)
    depth = np.array([0, 2, 0, 2, 1, 1, 1, 1], float)
    tris = np.array([[0, 1, 2], [1, 3, 2], [4, 5, 6], [5, 7, 6]])
    tri_id, _ = rasterize(xy, depth, tris, (40, 40))
    row = tri_id[20]
    assert np.all(np.isin(row[2:19], [0, 1]))
    assert np.all(np.isin(row[21:39], [2, 3]))


def plane(n=12, z=0.0, size=2.0):
    g = np.linspace(-size / 2, size / 2, n)
    X, Y = np.meshgrid(g, g)
    verts = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    return verts, quads


@pytest.mark.parametrize("shading", ["gouraud", "flat"])
@pytest.mark.parametrize("fov", [0.0, 30.0])
def test_flat_plane_facing_the_camera_is_uniformly_lit(shading, fov):
    verts, quads = plane()
    light = Light(direction=(-0.35, 0.45, 1.0), ambient=0.2, diffuse=0.8)
    color = np.array([200.0, 180.0, 160.0])
    r = MeshRenderer(quads, verts, camera=Camera(fov=fov), size=(96, 96), shading=shading, color=color,
                     background=(0, 0, 0), light=light)
    img = r.render(verts).astype(int)
    covered = img.sum(-1) > 0
    assert covered.sum() > 0.3 * img.shape[0] * img.shape[1]
    vals = img[covered]
    assert np.all(vals.max(0) - vals.min(0) <= 1)  # uniform, up to rounding
    ldir = np.array(light.direction) / np.linalg.norm(light.direction)
    expected = color * (light.ambient + light.diffuse * ldir[2])
    np.testing.assert_allclose(vals.mean(0), expected, atol=1.0)


def test_plane_seen_from_behind_is_lit_too_and_a_tilted_plane_is_darker():
    verts, quads = plane()
    front = MeshRenderer(quads, verts, camera=Camera(fov=0), size=(64, 64), background=(0, 0, 0))
    back = MeshRenderer(quads, verts, camera=Camera(fov=0, yaw=180), size=(64, 64), background=(0, 0, 0))
    tilted = MeshRenderer(quads, verts, camera=Camera(fov=0, yaw=60), size=(64, 64), background=(0, 0, 0))
    f, b, t = (r.render(verts)[32, 32].astype(int) for r in (front, back, tilted))
    assert f.sum() > 0 and b.sum() > 0
    assert t.sum() < f.sum()


def test_camera_view_and_depth_order_in_3d():
    # Two parallel planes: the one at z = +1 faces the default camera (which looks along -z) and is in front.
    v1, q1 = plane(z=1.0)
    v2, q2 = plane(z=-1.0, size=3.0)
    verts = np.vstack([v1, v2])
    quads = np.vstack([q1, q2 + len(v1)])
    colors = np.vstack([np.tile([0, 0, 255], (len(v1), 1)), np.tile([255, 0, 0], (len(v2), 1))]).astype(float)
    for cam in (Camera(fov=0), Camera(fov=40), Camera(fov=40, yaw=180)):
        r = MeshRenderer(quads, verts, camera=cam, size=(64, 64), background=(0, 0, 0))
        px = r.render(verts, vertex_colors=colors)[32, 32].astype(int)
        if cam.yaw == 180:  # from behind, the larger far plane is now in front
            assert px[0] > 0 and px[2] == 0
        else:
            assert px[2] > 0 and px[0] == 0
    # perspective: the nearer plane looks larger than under the orthographic view at the same fill
    _, xy, depth = View.fit(verts, Camera(fov=60), (64, 64)).project(verts)
    assert np.all(depth[: len(v1)] < depth[len(v1):])


def test_triangles_behind_the_camera_or_not_finite_are_dropped():
    xy = np.array([[1.0, 1.0], [14.0, 1.0], [1.0, 14.0], [np.nan, 3.0]])
    tri_id, _ = rasterize(xy, np.array([0.0, 0.0, 0.0, 0.0]), [[0, 1, 2], [0, 1, 3]], (16, 16))
    assert set(np.unique(tri_id)) == {-1, 0}
    tri_id, _ = rasterize(xy, np.array([0.0, np.inf, 0.0, 0.0]), [[0, 1, 2]], (16, 16))
    assert np.all(tri_id == -1)


def test_triangulate_fans_ngons():
    tris = triangulate([[0, 1, 2], [3, 4, 5, 6, 7]])
    np.testing.assert_array_equal(tris, [[0, 1, 2], [3, 4, 5], [3, 5, 6], [3, 6, 7]])


def test_vertex_normals_of_a_plane_point_up_z():
    verts, quads = plane()
    n = vertex_normals(verts, triangulate(quads))
    np.testing.assert_allclose(n, np.tile([0, 0, 1.0], (len(verts), 1)), atol=1e-12)


def test_bad_inputs_are_shape_errors():
    with pytest.raises(ShapeError, match=r"xy: expected shape \(N, 2\)"):
        rasterize(np.zeros((3, 3)), np.zeros(3), [[0, 1, 2]], (8, 8))
    with pytest.raises(ShapeError, match="vertex ids"):
        rasterize(np.zeros((3, 2)), np.zeros(3), [[0, 1, 3]], (8, 8))
    with pytest.raises(ShapeError, match=r"tris: expected shape \(M, 3\)"):
        rasterize(np.zeros((4, 2)), np.zeros(4), [[0, 1, 2, 3]], (8, 8))
    verts, quads = plane()
    r = MeshRenderer(quads, verts, size=(16, 16))
    with pytest.raises(ShapeError, match=r"expected shape \(144, 3\)"):
        r.render(verts[:10])
    with pytest.raises(ValueError, match="fov"):
        Camera(fov=180)


def _shells(rng, n_shells=4, n=14):
    """Nested, jittered spheres (an outer surface hiding inner shells, like eyes and teeth behind a face)."""
    th, ph = np.meshgrid(np.linspace(0.2, np.pi - 0.2, n), np.linspace(0, 2 * np.pi, n, endpoint=False), indexing="ij")
    unit = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    nxt = np.roll(idx, -1, axis=1)
    quads = np.stack([idx[:-1], nxt[:-1], nxt[1:], idx[1:]], -1).reshape(-1, 4)
    verts, faces = [], []
    for s in range(n_shells):
        r = 1.0 - 0.2 * s
        verts.append(unit * r + rng.normal(scale=0.01, size=unit.shape) + [0.1 * s, 0, 0])
        faces.append(quads + s * len(unit))
    return np.vstack(verts), np.vstack(faces)


@pytest.mark.parametrize("camera", [Camera(), Camera(yaw=70, pitch=-20), Camera(yaw=180, fov=0)])
def test_drawing_last_frames_visible_triangles_first_changes_no_pixel(camera):
    """MeshRenderer skips triangles provably behind the surface drawn first; the picture is the full z-buffer's."""
    rng = np.random.default_rng(2)
    V, F = _shells(rng)
    seq = [V + rng.normal(scale=0.02, size=V.shape) * t for t in range(6)]
    seq.append(seq[-1] * [1, -1, 1])  # a jump: last frame's visible set is a poor guess
    ours = MeshRenderer(F, V, camera=camera, size=(96, 80))
    n_culled = 0
    for v in seq:
        fresh = MeshRenderer(F, V, camera=camera, size=(96, 80))  # no previous frame: every triangle drawn
        first = ours._visible
        got, want = ours.render(v), fresh.render(v)
        assert got.tobytes() == want.tobytes()
        if first is not None:
            from retarget_cli.methods.render import _hidden, _scan, _setup

            _, xy, depth = ours.view.project(v)
            c = _setup(xy, depth, ours.tris, 96, 80)
            keys = np.full(96 * 80, np.iinfo(np.int64).max, dtype=np.int64)
            pri = first[c["ids"]]
            _scan(c, keys, 96, np.flatnonzero(pri))
            rest = np.flatnonzero(~pri)
            hidden = rest[_hidden(c, keys, 96, rest)]
            after = keys.copy()
            _scan(c, after, 96, hidden)
            assert np.array_equal(after, keys)  # no skipped triangle had a winning fragment
            n_culled += len(hidden)
    assert n_culled > 0  # the inner shells were skipped at least sometimes

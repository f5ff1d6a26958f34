"""The landmark map found automatically: which rig vertex is each of the 68 tracked landmarks.

A rig retargeted by its landmarks needs the vertex under each of the 68
Multi-PIE landmarks (Gross et al. 2010; the iBUG 300-W layout of Sagonas et
al. 2013), in order. :func:`find_landmark_map` finds them the way a person
would: it renders the rig's neutral face-on with the built-in rasteriser
(:mod:`retarget_cli.methods.render`), places the 68 points on the picture
with the pretrained detector the tracker uses (dlib's HOG face detector and
the ensemble of regression trees of Kazemi & Sullivan 2014,
:mod:`retarget_cli.methods.tracking.detect`), and lifts each point to the
mesh: the nearest vertex, in the picture, of the visible skin (the mesh's
connected piece under most of the points; eyeballs, teeth and mouth shells
are other pieces). Jaw-line points 0-16 lie on the face's outline, where the
same rule picks the nearest visible vertex.

Where the detector finds no face in any of the render styles
(:data:`STYLES`, tried in order: stylised or low-poly characters whose eyes
and mouth are painted in a texture), the sliders say where the face is
(:func:`slider_landmarks`): the blink shapes move the upper lids most, the
jaw-open / mouth-open shapes the chin, the smile shapes the mouth corners,
the brow shapes the brows. Those anchors place a 68-point template (the ICT
FaceKit's shipped map seen face-on, :data:`TEMPLATE_68`) by an affine fit,
and the points the sliders see are then taken from the sliders. Each point
says where it came from (:attr:`LandmarkMap.source`).

:func:`map_quality` measures a map (mirror symmetry of the left/right
pairs, inter-ocular distance, points per region and source, vertices used
twice). Pure: arrays in, arrays out; the detector is passed in.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import ParameterError, ShapeError
from .render import Camera, MeshRenderer, View, rasterize, triangulate, vertex_normals

log = logging.getLogger(__name__)

#: Number of landmarks of the layout.
N_POINTS = 68

#: Regions of the 68-point layout (0-based ids). "right"/"left" are the image's, face-on.
REGIONS_68 = {
    "jaw": tuple(range(0, 17)),
    "brow_right": tuple(range(17, 22)), "brow_left": tuple(range(22, 27)),
    "nose": tuple(range(27, 36)),
    "eye_right": tuple(range(36, 42)), "eye_left": tuple(range(42, 48)),
    "mouth": tuple(range(48, 68)),
}

#: Mirror pairs of the 68-point layout (image-left point, image-right point).
MIRROR_68 = tuple([(i, 16 - i) for i in range(8)] + [(17 + i, 26 - i) for i in range(5)]
                  + [(31, 35), (32, 34), (36, 45), (37, 44), (38, 43), (39, 42), (40, 47), (41, 46),
                     (48, 54), (49, 53), (50, 52), (59, 55), (58, 56), (60, 64), (61, 63), (67, 65)])

#: The 68 points of the ICT FaceKit's shipped map (its ``idx_to_landmark_verts``, MIT), seen face-on:
#: x to the image's right, y down, in inter-ocular distances (outer eye corners 36-45) from their midpoint.
#: The fallback's face template.
TEMPLATE_68 = np.array([
    [-0.826, -0.027], [-0.816, 0.218], [-0.778, 0.437], [-0.735, 0.649], [-0.642, 0.888], [-0.482, 1.081],
    [-0.342, 1.16], [-0.172, 1.199], [0.0, 1.233], [0.172, 1.199], [0.342, 1.16], [0.482, 1.081], [0.642, 0.888],
    [0.735, 0.649], [0.778, 0.437], [0.816, 0.218], [0.826, -0.027], [-0.652, -0.198], [-0.553, -0.285],
    [-0.425, -0.317], [-0.271, -0.309], [-0.131, -0.278], [0.131, -0.278], [0.271, -0.309], [0.425, -0.317],
    [0.553, -0.285], [0.652, -0.198], [0.0, -0.035], [0.0, 0.089], [0.0, 0.204], [0.0, 0.339], [-0.141, 0.513],
    [-0.068, 0.512], [0.0, 0.52], [0.068, 0.512], [0.141, 0.513], [-0.5, 0.0], [-0.434, -0.05], [-0.312, -0.057],
    [-0.207, 0.02], [-0.306, 0.039], [-0.432, 0.04], [0.207, 0.02], [0.312, -0.057], [0.434, -0.05], [0.5, 0.0],
    [0.432, 0.04], [0.306, 0.039], [-0.284, 0.78], [-0.191, 0.696], [-0.082, 0.656], [0.0, 0.663], [0.082, 0.656],
    [0.191, 0.696], [0.284, 0.78], [0.202, 0.84], [0.116, 0.867], [0.0, 0.876], [-0.116, 0.867], [-0.202, 0.84],
    [-0.248, 0.776], [-0.112, 0.755], [0.0, 0.758], [0.112, 0.755], [0.248, 0.776], [0.12, 0.764], [0.0, 0.766],
    [-0.12, 0.764]])

#: Each brow point's (17-26) least height above the line through the outer eye corners (36, 45), in inter-ocular
#: distances: where the detector places eyebrows on real faces. The mean of the three shared clips' frame-0
#: annotations (``../shared/realdata/videos/d{3,9,12}_00000.pts``, a pretrained 68-point detector's; per face
#: 0.206, 0.256 and 0.276 on average), each mirror pair averaged (``python bench/landmark_map.py`` prints it).
#: On an untextured render the detector marks the brow ridge's crest (0.199 on the ICT FaceKit's neutral), below
#: the hair that it marks on a face.
BROW_HEIGHT_68 = np.array([0.170, 0.266, 0.298, 0.278, 0.218, 0.218, 0.278, 0.298, 0.266, 0.170])

#: The fallback's eye: the vertices a blink moves at least this share of its most moved one.
EYE_SHARE = 0.25

#: The fallback's chin: the lowest vertex of the face's middle column moved this share of the most by jaw-open.
CHIN_SHARE = 0.85

#: Slider-name patterns (regular expressions, any case) of the shapes the fallback reads.
SLIDER_PATTERNS = {
    "blink": r"blink|eye_?close",
    "jaw": r"jaw_?open|mouth_?open|^aa?$|^ah$|ae_aa",
    "smile": r"smile|^joy$|^happy$|^fun$",
    "brow": r"brow",
}


@dataclass(frozen=True)
class RenderStyle:
    """How the neutral is drawn for the detector.

    Attributes
    ----------
    name : str
    size : int
        Image side in pixels; the face region fills :attr:`fill` of it.
    fill : float
        Fraction of the image the face region's bounding sphere covers.
    shading : {"gouraud", "flat"}
    color, background : (3,) BGR
    inside : float
        Brightness (a factor on *color*) of the mesh's inside where it shows through an opening: vertices
        whose normal faces away from the camera (:func:`render_face`).
    """

    name: str
    size: int = 512
    fill: float = 0.9
    shading: str = "gouraud"
    color: tuple = (150, 170, 215)
    background: tuple = (40, 36, 32)
    inside: float = 0.15


#: Render styles tried in order until the detector finds a face (measured by ``bench/landmark_map.py``).
STYLES = (
    RenderStyle("grey", background=(128, 128, 128)),
    RenderStyle("plain"),
    RenderStyle("skin", color=(125, 160, 225), background=(110, 110, 110), shading="flat"),
    RenderStyle("large", size=1024, background=(128, 128, 128)),
)


@dataclass
class FaceRender:
    """A face-on render of a mesh and what the lift needs of it.

    Attributes
    ----------
    image : ndarray (H, W, 3), uint8
        BGR.
    xy : ndarray (N, 2), float64
        Every vertex projected to the image (pixels).
    cam : ndarray (N, 3), float64
        Camera-space positions (x right, y up, z toward the viewer).
    tri_id : ndarray (H, W), int32
        Visible triangle per pixel (``-1``: background).
    visible : ndarray (N,), bool
        Vertices of a triangle that covers a pixel.
    yaw : float
        Camera yaw (degrees) that shows the face.
    style : RenderStyle
    view : View
        The camera (:meth:`~retarget_cli.methods.render.View.project` places other poses).
    vertices : ndarray (N, 3)
        The mesh rendered.
    normals : ndarray (N, 3), float64
        Camera-space unit vertex normals (area-weighted).
    region : ndarray (N,), bool
        The face: the vertices the sliders move (:func:`face_region`), on which the camera is framed.
    tris : ndarray (M, 3), int, optional
        The mesh's triangles (:func:`chin_ridge` reads the surface's curvature from them).
    """

    image: np.ndarray
    xy: np.ndarray
    cam: np.ndarray
    tri_id: np.ndarray
    visible: np.ndarray
    yaw: float
    style: RenderStyle
    view: View
    vertices: np.ndarray
    normals: np.ndarray
    region: np.ndarray
    tris: np.ndarray | None = None


@dataclass
class LandmarkMap:
    """A landmark-to-vertex map and how it was found.

    Attributes
    ----------
    vertices : ndarray (68,), int64
        Rig vertex of each landmark.
    points : ndarray (68, 2), float64
        Each landmark in :attr:`render`'s image (pixels): where it was placed.
    source : list of str
        Per landmark: ``detector``, ``detector:brow height`` (a brow point
        :func:`raise_brows` moved up), ``sliders:blink``, ``sliders:jaw``,
        ``sliders:smile``, ``sliders:brow``, ``template`` or ``user``.
    render : FaceRender
        The picture the points were placed on.
    skin : ndarray (N,), bool
        The vertices the points may be lifted to (visible skin).
    found_by : str
        The render style with which the detector found the face, or
        ``sliders`` when it found none.
    """

    vertices: np.ndarray
    points: np.ndarray
    source: list
    render: FaceRender
    skin: np.ndarray
    found_by: str
    tried: list = field(default_factory=list)


# --------------------------------------------------------------------------- the view


def motion_weights(deltas) -> np.ndarray:
    """Per-vertex motion: the sum over sliders of each vertex's displacement length; (n, N, 3) -> (N,)."""
    D = np.asarray(deltas, np.float64)
    if D.ndim != 3 or D.shape[2] != 3:
        raise ShapeError(f"deltas: expected shape (n, N, 3), got {D.shape}")
    return np.sqrt((D * D).sum(2)).sum(0)


def front_yaw(vertices, tris, motion) -> float:
    """Camera yaw (degrees) that faces the face: the motion-weighted mean normal, y up.

    The vertices the sliders move (lips, lids, brows, cheeks) face forward
    mostly, so their normals weighted by their motion point out of the face:
    the ICT FaceKit's +z, a VRM 0.x avatar's -z. Only the horizontal (x, z)
    part is used: the model's y is taken as up (glTF, OBJ heads).

    Parameters
    ----------
    vertices : ndarray (N, 3)
    tris : ndarray (M, 3), int
    motion : ndarray (N,)
        :func:`motion_weights`.
    """
    n = vertex_normals(np.asarray(vertices, np.float64), tris)
    f = (n * np.asarray(motion, np.float64)[:, None]).sum(0)
    if np.hypot(f[0], f[2]) < 1e-12:
        return 0.0
    return float(np.degrees(np.arctan2(-f[0], f[2])))


def face_region(vertices, motion, *, share: float = 0.05) -> np.ndarray:
    """The vertices the sliders move: motion above *share* of its 99th percentile; (N,) bool.

    Falls back to every vertex when no vertex moves.
    """
    m = np.asarray(motion, np.float64)
    top = np.percentile(m[m > 0], 99) if (m > 0).any() else 0.0
    if top <= 0:
        return np.ones(len(vertices), bool)
    return m > share * top


def render_face(vertices, tris, region, yaw: float, style: RenderStyle = STYLES[0]) -> FaceRender:
    """Render *vertices* face-on at *yaw*, framed on the *region* vertices (the face).

    The skin is one colour, lit (the style's shading); where the inside of the
    mesh shows through an opening (vertices whose normal faces away from the
    camera: the back of the head seen through eye holes when the rig has no
    eyeballs, the inner side of a lid or a lip) it is drawn at
    :attr:`RenderStyle.inside` of that colour, dark, as a real eye's or mouth's
    opening looks to the detector. Lit from the front, the inside would read as
    skin and the eye as a bump (measured on the VALID head: symmetry of the map
    0.089 mean inter-ocular distances lit, 0.049 dark; ``bench/landmark_map.py``).

    Parameters
    ----------
    vertices : ndarray (N, 3)
    tris : ndarray (M, 3), int
    region : ndarray (N,), bool
        Vertices the camera frames (:func:`face_region`).
    yaw : float
        Degrees (:class:`~retarget_cli.methods.render.Camera`).
    style : RenderStyle
    """
    V = np.asarray(vertices, np.float64)
    cam = Camera(yaw=yaw, fov=20, fill=style.fill)
    size = (style.size, style.size)
    ren = MeshRenderer(tris, V, camera=cam, size=size, shading=style.shading, color=style.color,
                       background=style.background, frame=V[region])
    cam_pos, xy, depth = ren.view.project(V)
    normals = vertex_normals(cam_pos, ren.tris)
    inside = _view_cosine(cam_pos, normals, cam.fov == 0) < 0
    image = ren.render(V, vertex_colors=np.where(inside[:, None], style.inside, 1.0) * np.asarray(style.color, float))
    tri_id, bary = rasterize(xy, depth, ren.tris, size)
    visible = _visible_vertices(cam_pos, xy, ren.tris, tri_id, bary, 0.01 * ren.view.radius, cam.fov == 0, normals)
    return FaceRender(image, xy, cam_pos, tri_id, visible, float(yaw), style, ren.view, V, normals,
                      np.asarray(region, bool), np.asarray(ren.tris))


def _visible_vertices(cam, xy, tris, tri_id, bary, tol: float, ortho: bool, normals) -> np.ndarray:
    """Vertices not hidden: of a triangle that covers a pixel, facing the camera, not behind the surface at their pixel.

    Facing: the vertex normal (area-weighted) has a cosine above -0.1 with the
    direction to the camera (the inside of the back of the head, seen through
    an eye hole of a rig without eyeballs, faces away).
    The surface's depth at a vertex's pixel is its triangle's camera-space z
    interpolated with the pixel's barycentrics; a vertex more than *tol*
    (model units) behind it is hidden (the inside of a silhouette triangle,
    the neck under the chin). A vertex whose pixel is background or outside
    the image keeps the first test (on the outline).
    """
    H, W = tri_id.shape
    drawn = np.zeros(len(xy), bool)
    won = np.unique(tri_id[tri_id >= 0])
    drawn[tris[won].ravel()] = True
    with np.errstate(invalid="ignore"):
        p = np.rint(np.nan_to_num(xy, nan=-1.0)).astype(np.int64)
    inside = (p[:, 0] >= 0) & (p[:, 0] < W) & (p[:, 1] >= 0) & (p[:, 1] < H)
    t = np.full(len(xy), -1, np.int64)
    t[inside] = tri_id[p[inside, 1], p[inside, 0]]
    has = np.flatnonzero(t >= 0)
    surface = (cam[tris[t[has]], 2] * bary[p[has, 1], p[has, 0]]).sum(1)
    visible = drawn.copy()
    visible[has] &= cam[has, 2] >= surface - tol
    return visible & (_view_cosine(cam, normals, ortho) > -0.1)


def _view_cosine(cam, normals, ortho: bool) -> np.ndarray:
    """Cosine between each vertex normal and the direction to the camera; (N,)."""
    to_camera = np.array([0.0, 0.0, 1.0]) if ortho else -cam
    return (normals * to_camera).sum(1) / np.maximum(np.linalg.norm(to_camera, axis=-1), 1e-300)


def mesh_pieces(vertices, tris, *, weld: bool = True) -> np.ndarray:
    """Connected piece of each vertex; (N,) int.

    Vertices are joined by triangles and, with *weld*, by sharing a position
    (to 1e-6 of the mesh's size: glTF files split vertices along UV and
    normal seams).
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    V = np.asarray(vertices, np.float64)
    t = np.asarray(tris, np.int64)
    scale = max(float(np.ptp(V, axis=0).max()), 1e-300)
    if weld:
        _, same = np.unique(np.round(V / (1e-6 * scale)).astype(np.int64), axis=0, return_inverse=True)
        same = same.ravel()
    else:
        same = np.arange(len(V))
    n = len(V)
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2], np.arange(n)])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0], n + same])
    g = sp.coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n + same.max() + 1,) * 2)
    return connected_components(g, directed=False)[1][:n]


def skin_vertices(render: FaceRender, tris, points=None) -> np.ndarray:
    """The visible vertices of the face's connected piece; (N,) bool.

    The piece is the one under most of *points* (68, 2) when given, else the
    one that covers the most pixels (the skin, not an eyeball or a tooth).
    Pieces are joined by triangles; when the piece found so holds less than
    :data:`WELD_BELOW` of the visible vertices, vertices that share a
    position are joined too (a glTF face split along its UV seams). Not
    always: the ICT FaceKit's eye occlusion shells share its lids' positions.
    """
    tris = np.asarray(tris, np.int64)
    skin = _skin_piece(render, tris, points, weld=False)
    if skin.sum() < WELD_BELOW * render.visible.sum():
        skin = _skin_piece(render, tris, points, weld=True)
    return skin


def _skin_piece(render: FaceRender, tris, points, *, weld: bool) -> np.ndarray:
    pieces = mesh_pieces(render.vertices, tris, weld=weld)
    hit = np.zeros(0, np.int64)
    if points is not None:
        H, W = render.tri_id.shape
        p = np.rint(np.asarray(points)).astype(np.int64)
        ok = (p[:, 0] >= 0) & (p[:, 0] < W) & (p[:, 1] >= 0) & (p[:, 1] < H)
        hit = render.tri_id[p[ok, 1], p[ok, 0]]
        hit = hit[hit >= 0]
    if not len(hit):
        hit = render.tri_id[render.tri_id >= 0]
    if not len(hit):
        return render.visible.copy()
    piece = np.bincount(pieces[tris[hit, 0]]).argmax()
    return render.visible & (pieces == piece)


def lift(points, render: FaceRender, skin) -> np.ndarray:
    """The skin vertex nearest each image point: (P, 2) pixels -> (P,) vertex ids.

    The nearest in the image among the visible skin vertices: under an inner
    point it is a vertex of the visible triangle there (on a dense mesh), on
    the outline (jaw points 0-16) the outline's nearest vertex.
    """
    from scipy.spatial import cKDTree

    ids = np.flatnonzero(skin)
    if not len(ids):
        raise ShapeError("no visible skin vertex to place the landmarks on")
    _, k = cKDTree(render.xy[ids]).query(np.asarray(points, np.float64).reshape(-1, 2))
    return ids[k]


#: :func:`skin_vertices` welds the mesh when the skin piece holds less than this share of the visible vertices.
WELD_BELOW = 0.25

#: Jaw-line points (on the face's outline face-on).
CONTOUR_68 = tuple(range(17))
#: Jaw-line points on the cheeks' outline face-on (the fallback's :func:`_outline` moves these too); 5-11 are
#: on the chin, which faces the camera.
CHEEK_68 = (0, 1, 2, 3, 4, 12, 13, 14, 15, 16)
#: Radius (inter-ocular distances, in the image) around a jaw-line point in which its vertex is chosen.
CONTOUR_RADIUS = 0.02


def lift_landmarks(points, render: FaceRender, skin, *, smooth: bool = True, ridge: bool = True) -> np.ndarray:
    """The 68 points lifted to vertices: :func:`lift`, and on the jaw line by the surface's depth.

    A jaw-line point sits on or near the outline, where the surface turns
    away from the camera and vertices at very different depths project
    within a pixel of each other. Of the visible skin vertices within
    :data:`CONTOUR_RADIUS` inter-ocular distances of the point:

    - on the cheeks (:data:`CHEEK_68`) the vertex of the occluding contour,
      the one whose normal is most nearly perpendicular to the view (the
      contour generator: the outline seen face-on is made of it), among the
      face's vertices (:attr:`FaceRender.region`, what the sliders move: not
      an ear or the back of the head that project there too);
    - on the chin (5-11), which faces the camera, and where no face vertex is
      near, the one nearest the camera (the jaw, not the neck under it).

    With *smooth* the cheek points are then chosen again together, so that
    the jaw line 0-16 is a smooth curve in 3D (:func:`smooth_jaw`, anchored
    on the chin points as lifted here); with *ridge* the chin points
    :data:`RIDGE_68` are then moved onto the jaw's edge, the crease where the
    surface curves most across the jaw line (:func:`chin_ridge`; needs
    :attr:`FaceRender.tris`). Measured on the ICT FaceKit (``bench/landmark_map.py``).

    Parameters
    ----------
    points : ndarray (68, 2)
        Pixels in *render*'s image.
    render : FaceRender
    skin : ndarray (N,), bool
    smooth : bool
        Choose the cheek points' vertices together (:func:`smooth_jaw`).
    ridge : bool
        Move the chin points onto the jaw's edge (:func:`chin_ridge`).

    Returns
    -------
    ndarray (68,), int64
    """
    P = np.asarray(points, np.float64)
    vx = lift(P, render, skin)
    iod = np.linalg.norm(P[45] - P[36])
    ids = np.flatnonzero(skin)
    grazing = np.abs(_view_cosine(render.cam, render.normals, render.view.camera.fov == 0))
    for i in CONTOUR_68:
        near = ids[np.linalg.norm(render.xy[ids] - P[i], axis=1) < CONTOUR_RADIUS * iod]
        if not len(near):
            continue
        face = near[render.region[near]]
        if i in CHEEK_68 and len(face):
            vx[i] = face[np.argmin(grazing[face])]
        else:
            vx[i] = near[np.argmax(render.cam[near, 2])]
    if smooth:
        vx[list(CONTOUR_68)] = smooth_jaw(P, vx, render, skin)
    if ridge and render.tris is not None:
        vx[list(RIDGE_68)] = chin_ridge(P, vx, render, skin)
    return vx


#: Chin points of the jaw line (they face the camera; :func:`chin_ridge`).
CHIN_68 = (5, 6, 7, 8, 9, 10, 11)
#: Chin points :func:`chin_ridge` moves onto the jaw's edge: not 5 and 11, where the jaw turns to the cheek (there
#: it made the VALID head's map less symmetric, 0.043 -> 0.050 inter-ocular distances, ``bench/landmark_map.py``).
RIDGE_68 = (6, 7, 8, 9, 10)
#: Half-width (inter-ocular distances, in the image) of the strip across the jaw line through a chin point in
#: which :func:`chin_ridge` looks, and how far across the line it looks on either side.
CHIN_BAND = 0.03
CHIN_REACH = 0.06
#: :func:`chin_ridge`: candidates curving across the jaw line at least this share as much as the most curved one
#: are equal, and the one nearest the camera of them is taken (on a sphere: every vertex, the front-most).
CHIN_TIE = 0.9


def surface_curvature(vertices, normals, tris, ids, directions) -> np.ndarray:
    """Normal curvature of a mesh at some vertices along given directions; (K,), positive where it is convex.

    At each vertex the derivative of the unit normal (the shape operator, extended to 3D) is fitted by least
    squares to the normals' changes along the edges to its 2-ring neighbours, :math:`\\Delta n \\approx J
    \\Delta x`, and the curvature along the unit tangent :math:`t` (the direction projected onto the vertex's
    tangent plane) is :math:`t^\\top J t` (:math:`1/r` on a sphere of radius :math:`r` with outward normals).

    Parameters
    ----------
    vertices : ndarray (N, 3)
    normals : ndarray (N, 3)
        Unit vertex normals, outward.
    tris : ndarray (M, 3), int
    ids : ndarray (K,), int
    directions : ndarray (K, 3) or (3,)

    Returns
    -------
    ndarray (K,), float64
        In inverse units of *vertices*; 0 at a vertex with fewer than three neighbours.
    """
    import scipy.sparse as sp

    X, N = np.asarray(vertices, np.float64), np.asarray(normals, np.float64)
    t = np.asarray(tris, np.int64)
    n = len(X)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A = A + A.T
    A = (A @ A + A).tocsr()
    ids = np.asarray(ids, np.int64)
    dirs = np.broadcast_to(np.asarray(directions, np.float64), (len(ids), 3))
    out = np.zeros(len(ids))
    for j, (v, a) in enumerate(zip(ids, dirs)):
        nb = A.indices[A.indptr[v]:A.indptr[v + 1]]
        nb = nb[nb != v]
        if len(nb) < 3:
            continue
        J, *_ = np.linalg.lstsq(X[nb] - X[v], N[nb] - N[v], rcond=None)
        tan = a - (a @ N[v]) * N[v]
        norm = np.linalg.norm(tan)
        if norm > 0:
            tan = tan / norm
            out[j] = tan @ J @ tan
    return out


def chin_ridge(points, vx, render: FaceRender, skin) -> np.ndarray:
    """The chin points' vertices on the jaw's edge: the most convex crease across the jaw line; (5,) vertex ids.

    On the render the detector puts the chin points (6-10) where the shading
    of the under-chin begins, the light's terminator (on the ICT FaceKit with
    the default light, points 7-9 0.03-0.04 inter-ocular distances below the
    chin vertices its map ships, 6-10 0.04-0.10 behind them). A face's jaw line is the edge
    where its front turns under: the surface curves most across the line
    there. For each chin point, among the face's visible skin vertices
    (:attr:`FaceRender.region`) in the strip across the jaw line through it
    (within :data:`CHIN_BAND` inter-ocular distances of that line and
    :data:`CHIN_REACH` of the point, in the picture; the line's direction
    from the neighbouring points), the one whose surface curves most across
    the line (:func:`surface_curvature` along the line's normal in the
    picture, turned into the vertex's tangent plane) is taken; candidates
    within :data:`CHIN_TIE` of the most curved are equal, and the one nearest
    the camera wins (a sphere, equally curved everywhere: the front-most, as
    before). A point with no candidate, or none curving convexly, keeps its
    vertex. Measured with ``bench/landmark_map.py`` (docs/landmark-map.md).

    Parameters
    ----------
    points : ndarray (68, 2)
        Pixels of *render*.
    vx : ndarray (68,), int
        The map as lifted point by point.
    render : FaceRender
        With :attr:`FaceRender.tris`.
    skin : ndarray (N,), bool

    Returns
    -------
    ndarray (5,), int64
        Vertices of points :data:`RIDGE_68` (6-10).
    """
    P = np.asarray(points, np.float64)
    out = np.asarray(vx, np.int64)[list(RIDGE_68)].copy()
    iod = np.linalg.norm(P[45] - P[36])
    if not iod > 0 or render.tris is None:
        return out
    centre = P[27:68].mean(0)
    pool = np.flatnonzero(np.asarray(skin, bool) & render.region)
    strips, dirs = [], []
    for i in RIDGE_68:
        along = P[i + 1] - P[i - 1]
        if not np.linalg.norm(along) > 0:
            strips.append(pool[:0])
            continue
        along = along / np.linalg.norm(along)
        across = np.array([along[1], -along[0]])
        if across @ (P[i] - centre) < 0:
            across = -across
        off = render.xy[pool] - P[i]
        strips.append(pool[(np.abs(off @ along) < CHIN_BAND * iod) & (np.abs(off @ across) < CHIN_REACH * iod)])
        dirs.append(np.broadcast_to([across[0], -across[1], 0.0], (len(strips[-1]), 3)))
    if not sum(len(s) for s in strips):
        return out
    k_all = surface_curvature(render.cam, render.normals, render.tris, np.concatenate(strips), np.concatenate(dirs))
    start = 0
    for j, near in enumerate(strips):
        k = k_all[start:start + len(near)]
        start += len(near)
        if not len(near) or not k.max() > 0:
            continue
        top = near[k >= CHIN_TIE * k.max()]
        out[j] = top[np.argmax(render.cam[top, 2])]
    return out


#: Radius (inter-ocular distances, in the image) around a cheek point in which :func:`smooth_jaw` looks.
JAW_RADIUS = 0.03
#: Cosine scale of the occluding contour in :func:`smooth_jaw`: a candidate's cost grows with the square of its
#: normal's cosine with the view in these units, and hidden face vertices with a cosine below it in absolute value
#: (the far side of the contour, behind the pixel's own front triangle) are candidates too.
JAW_GRAZING = 0.1
#: Weight of the jaw line's bending (squared second differences, inter-ocular distances) in :func:`smooth_jaw`.
JAW_SMOOTHNESS = 100.0


def smooth_jaw(points, vx, render: FaceRender, skin) -> np.ndarray:
    """The cheek points' vertices chosen so that the jaw line is a smooth curve in 3D; (17,) vertex ids.

    Near the outline the picture does not say how deep a point is: the
    cheek's side is nearly parallel to the view, so vertices a tenth of an
    inter-ocular distance apart in depth project within a pixel or two, and
    the most grazing vertex of each point alone (:func:`lift_landmarks`)
    jumps back and forth between them from one point to the next (on the
    ICT FaceKit, points 1-3 at +0.10, 0 and -0.10 inter-ocular distances
    from the kit's vertices in depth). A face's jaw line is a smooth curve
    (the ICT FaceKit's shipped points follow one), so the cheek points'
    (:data:`CHEEK_68`) vertices are chosen together: for each point the
    candidates are the face's vertices (:attr:`FaceRender.region`) within
    :data:`JAW_RADIUS` inter-ocular distances of it in the picture, visible
    skin or hidden on the far side of the contour (|cosine| of normal and
    view below :data:`JAW_GRAZING`); the chin points 5-11 (facing the
    camera, their depth seen) stay as lifted and anchor the curve. The
    choice minimises, by dynamic programming over the chain 0-16,

    .. math:: \\sum_i (d_i / r)^2 + (c_i / c_0)^2
              + \\lambda \\sum_i \\lVert X_{i-1} - 2 X_i + X_{i+1} \\rVert^2

    with :math:`d_i` a candidate's distance from its point in the picture,
    :math:`r` the radius, :math:`c_i` its normal's cosine with the view
    (0 on the occluding contour), :math:`c_0` = :data:`JAW_GRAZING`,
    :math:`X` camera-space positions in inter-ocular distances and
    :math:`\\lambda` = :data:`JAW_SMOOTHNESS`: each point near the contour,
    as :func:`lift_landmarks` puts it, unless the curve bends there. A point
    with no candidate keeps its vertex. Measured with ``bench/landmark_map.py``
    (docs/landmark-map.md).

    Parameters
    ----------
    points : ndarray (68, 2)
        The detected points (pixels of *render*).
    vx : ndarray (68,), int
        The map as lifted point by point.
    render : FaceRender
    skin : ndarray (N,), bool

    Returns
    -------
    ndarray (17,), int64
        Vertices of points 0-16.
    """
    P = np.asarray(points, np.float64)
    vx = np.asarray(vx, np.int64)
    iod = np.linalg.norm(P[45] - P[36])
    iod3 = np.linalg.norm(render.cam[vx[45]] - render.cam[vx[36]])
    if not (iod > 0 and iod3 > 0):
        return vx[list(CONTOUR_68)].copy()
    X = render.cam / iod3
    grazing = np.abs(_view_cosine(render.cam, render.normals, render.view.camera.fov == 0))
    pool = np.flatnonzero(render.region & (skin | (grazing < JAW_GRAZING)))
    cands, unary = [], []
    for i in CONTOUR_68:
        d = np.linalg.norm(render.xy[pool] - P[i], axis=1) / (JAW_RADIUS * iod)
        near = d < 1
        if i in CHEEK_68 and near.any():
            cands.append(pool[near])
            unary.append(d[near] ** 2 + (grazing[pool[near]] / JAW_GRAZING) ** 2)
        else:
            cands.append(vx[i:i + 1])
            unary.append(np.zeros(1))
    return _chain_path(cands, unary, X, JAW_SMOOTHNESS)


def _chain_path(cands, unary, X, lam: float) -> np.ndarray:
    """One candidate per link of a chain minimising the unary costs plus *lam* times the squared second differences.

    Dynamic programming over pairs of consecutive choices (Viterbi on a second-order chain).

    Parameters
    ----------
    cands : list of ndarray (K_i,), int
        Candidate vertex ids per link (at least 2 links).
    unary : list of ndarray (K_i,)
    X : ndarray (N, 3)
        Positions of the vertices.
    lam : float

    Returns
    -------
    ndarray (len(cands),), int64
    """
    n = len(cands)
    C = [X[c] for c in cands]
    cost = unary[0][:, None] + unary[1][None, :]  # (choice at i-1, choice at i)
    back = []
    for i in range(2, n):
        bend = C[i - 2][:, None, None, :] - 2 * C[i - 1][None, :, None, :] + C[i][None, None, :, :]
        total = cost[:, :, None] + lam * (bend ** 2).sum(-1)
        back.append(total.argmin(0))
        cost = total.min(0) + unary[i][None, :]
    b, c = np.unravel_index(int(np.argmin(cost)), cost.shape)
    path = [c, b]
    for i in range(n - 1, 1, -1):
        a = back[i - 2][b, c]
        path.append(a)
        b, c = a, b
    path = path[::-1]
    return np.array([cands[i][path[i]] for i in range(n)], np.int64)


# --------------------------------------------------------------------------- the detector


def detect_face(render: FaceRender, detector):
    """The 68 points the *detector* places on *render*'s image, or None when it finds no face.

    *detector* is a :class:`~retarget_cli.methods.tracking.detect.Detector`
    (or any object with its ``detect(gray)`` and ``landmarks(gray, box)``);
    the largest face is used.
    """
    import cv2

    gray = cv2.cvtColor(render.image, cv2.COLOR_BGR2GRAY)
    boxes = detector.detect(gray)
    if not len(boxes):
        return None
    box = boxes[int(np.argmax(boxes[:, 2] * boxes[:, 3]))]
    return np.asarray(detector.landmarks(gray, box), np.float64)


def raise_brows(points, heights=BROW_HEIGHT_68) -> tuple[np.ndarray, np.ndarray]:
    """Brow points (17-26) moved up to at least *heights* above the eye-corner line, across it.

    The detector, run on an untextured render, finds the brows on the brow ridge's crest, where the shading
    turns; on a face it marks the eyebrow hair above it. The mesh has no hair to show, so each brow point
    the render places lower than real faces carry theirs (:data:`BROW_HEIGHT_68`) is moved up, perpendicular
    to the line through the outer eye corners 36-45, to that height; a brow placed higher stays.

    Parameters
    ----------
    points : ndarray (68, 2)
        Image pixels (y down).
    heights : ndarray (10,)
        Least height of points 17-26, in inter-ocular distances.

    Returns
    -------
    points : ndarray (68, 2), float64
    moved : ndarray (68,), bool
    """
    P = np.array(points, np.float64)
    axis = P[45] - P[36]
    iod = float(np.linalg.norm(axis))
    moved = np.zeros(len(P), bool)
    if not iod > 0:
        return P, moved
    up = np.array([axis[1], -axis[0]]) / iod  # perpendicular, toward the brows (image y points down)
    brows = np.arange(17, 27)
    height = (P[brows] - (P[36] + P[45]) / 2) @ up / iod
    lift = np.maximum(np.asarray(heights, np.float64) - height, 0.0)
    P[brows] += lift[:, None] * iod * up
    moved[brows] = lift > 0
    return P, moved


def find_landmark_map(vertices, faces, deltas, names, *, detector=None, yaw: float | None = None,
                      styles=STYLES) -> LandmarkMap:
    """Find the rig vertex of each of the 68 landmarks on the rig's neutral.

    Parameters
    ----------
    vertices : ndarray (N, 3), float
        The neutral.
    faces : ndarray (F, n) or list of lists of int
        Polygons (0-based).
    deltas : ndarray (n, N, 3), float
        The sliders' displacements (they find the face and its front, and
        give the fallback's anchors).
    names : sequence of str
        Slider names (the fallback reads blink, jaw-open, smile and brow shapes by name).
    detector : Detector, optional
        The pretrained detector; None skips straight to the sliders' fallback.
    yaw : float, optional
        Camera yaw in degrees that shows the face (0: the face looks along
        +z, 180: along -z); default from the mesh (:func:`front_yaw`).
    styles : sequence of RenderStyle
        Renders tried in order until the detector finds a face.

    Returns
    -------
    LandmarkMap
    """
    V = np.asarray(vertices, np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or not len(V):
        raise ShapeError(f"vertices: expected shape (N, 3), got {V.shape}")
    tris = triangulate(faces)
    if not len(tris):
        raise ShapeError("faces: the mesh has no polygon to render")
    D = np.asarray(deltas, np.float64)
    if D.shape[1:] != V.shape or len(D) != len(names):
        raise ShapeError(f"deltas: expected shape ({len(names)}, {len(V)}, 3), got {D.shape}")
    if not styles:
        raise ParameterError("styles: expected at least one render style")
    motion = motion_weights(D)
    region = face_region(V, motion)
    yaw = front_yaw(V, tris, motion) if yaw is None else float(yaw)
    tried = []
    if detector is not None:
        for style in styles:
            render = render_face(V, tris, region, yaw, style)
            pts = detect_face(render, detector)
            tried.append(style.name)
            if pts is not None:
                log.info("landmark map: the detector found the face on the %r render (yaw %.0f)", style.name, yaw)
                pts, raised = raise_brows(pts)
                skin = skin_vertices(render, tris, pts)
                vx = part_closed_lips(lift_landmarks(pts, render, skin), pts, render, skin, V, D, names)
                source = ["detector:brow height" if r else "detector" for r in raised]
                return LandmarkMap(vx, pts, source, render, skin, style.name, tried)
        log.info("landmark map: no face found on the %s renders; placing the points from the sliders",
                 ", ".join(tried))
    render = render_face(V, tris, region, yaw, styles[0])
    skin = skin_vertices(render, tris)
    pts, vx, source = slider_landmarks(render, skin, V, D, names)
    return LandmarkMap(vx, pts, source, render, skin, "sliders", tried)


# --------------------------------------------------------------------------- the sliders' fallback


def slider_groups(names, patterns=None) -> dict:
    """Slider indices of each fallback category (blink, jaw, smile, brow) by name."""
    patterns = SLIDER_PATTERNS if patterns is None else patterns
    return {cat: [i for i, n in enumerate(names) if re.search(p, str(n), re.IGNORECASE)]
            for cat, p in patterns.items()}


def _side_max(values, mask, xy, mid, side):
    """Index of the largest *values* among *mask* on one side (-1 image left, +1 right) of x = *mid*."""
    m = mask & ((xy[:, 0] - mid) * side > 0)
    if not m.any():
        return None
    return int(np.flatnonzero(m)[np.argmax(values[m])])


def _affine(src, dst):
    """Least-squares 2D affine map (3, 2) taking *src* (K, 2) to *dst* (K, 2); similarity-like for K < 3."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if len(src) >= 3:
        A = np.c_[src, np.ones(len(src))]
        M, *_ = np.linalg.lstsq(A, dst, rcond=None)
        return M
    s = np.linalg.norm(dst[-1] - dst[0]) / max(np.linalg.norm(src[-1] - src[0]), 1e-12) if len(src) > 1 else 1.0
    t = dst.mean(0) - s * src.mean(0)
    return np.array([[s, 0.0], [0.0, s], t])


class _Cues:
    """What the sliders say on the render: per-vertex motion of each category, and where the closed lids go.

    Candidates are every visible vertex of any piece: a stylised face's eyes
    and mouth are often pieces of their own laid over a skin no slider moves.
    """

    def __init__(self, render: FaceRender, vertices, deltas, names):
        self.xy, self.cand = render.xy, render.visible
        groups = slider_groups(names)
        D = np.asarray(deltas, np.float64)
        self.motion = {c: (np.sqrt((D[ix] ** 2).sum(2)).max(0) if ix else None) for c, ix in groups.items()}
        self.closed = None
        if groups["blink"]:
            # each vertex moved by the blink that moves it most: the upper lid lands on the lower lid's line
            d = D[np.asarray(groups["blink"])]
            strongest = np.argmax((d ** 2).sum(2), axis=0)
            moved = np.asarray(vertices, np.float64) + d[strongest, np.arange(D.shape[1])]
            self.closed = render.view.project(moved)[1]
        self.opened = _opened(render, vertices, D, groups["jaw"])
        moved_any = self.cand & (motion_weights(D) > 0)
        self.mid = float(np.median(self.xy[moved_any if moved_any.any() else self.cand, 0]))

    def side(self, side: int) -> np.ndarray:
        """Candidates on one side of the face's middle (-1 image left, +1 right)."""
        return self.cand & ((self.xy[:, 0] - self.mid) * side > 0)


def _eye_anchors(cues: _Cues, side: int, first: int, anchors: dict) -> None:
    """Six eye points from the blinks: corners at the ends of the moved lid, upper lid where it moves most,
    lower lid the first vertex below where the closed lid lands. *side* -1: points 36-41, +1: 42-47."""
    m = cues.motion["blink"]
    pool = cues.side(side)
    if m is None or not pool.any() or m[pool].max() <= 0:
        return
    near = pool & (m > EYE_SHARE * m[pool].max())
    ids = np.flatnonzero(near)
    xy = cues.xy
    a, b = ids[xy[ids, 0].argmin()], ids[xy[ids, 0].argmax()]  # image-left and image-right ends of the moved lid
    anchors[first], anchors[first + 3] = (a, "sliders:blink"), (b, "sliders:blink")  # 36 -> 39, 42 -> 45 run right
    w = xy[b, 0] - xy[a, 0]
    down = np.clip(cues.closed[:, 1] - xy[:, 1], 0, None)  # how far each vertex comes down the picture
    for j, t in ((1, 1 / 3), (2, 2 / 3)):
        band = near & (np.abs(xy[:, 0] - (xy[a, 0] + t * w)) < max(w / 8, 1.0))
        k = np.flatnonzero(band if band.any() else near)
        k = k[np.argmax(down[k])] if down[k].max() > 0 else k[np.argmax(m[k])]
        anchors[first + j] = (k, "sliders:blink")
        # below 37 is 41, below 38 is 40 (43/47, 44/46)
        low = cues.closed[k]
        under = pool & (np.abs(xy[:, 0] - low[0]) < max(w / 8, 1.0)) & (xy[:, 1] >= low[1] - 1.0)
        if under.any():
            u = np.flatnonzero(under)
            anchors[first + (5 if j == 1 else 4)] = (u[np.argmin(xy[u, 1])], "sliders:blink")


def _mouth_anchors(cues: _Cues, anchors: dict) -> None:
    """Mouth corners where the smiles move most on each side; the chin from jaw-open (see slider_landmarks)."""
    xy = cues.xy
    m = cues.motion["smile"]
    if m is not None:
        for side, idx in ((-1, 48), (1, 54)):
            pool = np.flatnonzero(cues.side(side))
            if len(pool) and m[pool].max() > 0:
                anchors[idx] = (pool[np.argmax(m[pool])], "sliders:smile")
    m = cues.motion["jaw"]
    if m is not None and m[cues.cand].max(initial=0) > 0:
        span = np.ptp(xy[cues.cand, 0])
        central = cues.cand & (np.abs(xy[:, 0] - cues.mid) < 0.05 * span) & (m > 0)
        pool = central if central.any() else cues.cand
        strong = np.flatnonzero(pool & (m >= CHIN_SHARE * m[pool].max()))
        anchors[8] = (strong[np.argmax(xy[strong, 1])], "sliders:jaw")


def slider_landmarks(render: FaceRender, skin, vertices, deltas, names):
    """The 68 landmarks placed from what the sliders move (when the detector finds no face).

    Anchors, each a vertex: per eye the blink shapes' moved lid (corners at
    the ends of the region they move at least :data:`EYE_SHARE` as much as
    their most moved vertex on that side, upper-lid points where they move
    most down the picture in the lid's thirds, lower-lid points the first vertex below where
    the closed upper lid lands); the mouth corners where the smile shapes
    move most on each side; the chin, the lowest vertex of the face's middle
    column among those the jaw-open shapes move at least :data:`CHIN_SHARE`
    as much as the most moved one there. A 68-point face template
    (:data:`TEMPLATE_68`) is fitted to the anchors (2D affine, least squares)
    and gives every other point, lifted to the *skin*; template jaw points
    0-4 and 12-16 move along their row to the outline; brow points move to
    where the brow shapes move most in their column; lip points that landed on
    a vertex no mouth slider moves go onto the lips jaw-open parts (:func:`_lips`).

    Parameters
    ----------
    render : FaceRender
    skin : ndarray (N,), bool
        Vertices the template's points are lifted to.
    vertices : ndarray (N, 3)
        The neutral.
    deltas : ndarray (n, N, 3)
    names : sequence of str

    Returns
    -------
    points : ndarray (68, 2), float64
        Pixels in *render*'s image.
    vertices : ndarray (68,), int64
    source : list of str
        Where each point came from.
    """
    cues = _Cues(render, vertices, deltas, names)
    anchors: dict[int, tuple[int, str]] = {}
    _eye_anchors(cues, -1, 36, anchors)
    _eye_anchors(cues, 1, 42, anchors)
    _mouth_anchors(cues, anchors)
    _check_chin(anchors, render.xy)
    _brows(anchors, cues, _place_template(anchors, render.xy, skin))
    pts = _place_template(anchors, render.xy, skin)
    vx = lift_landmarks(pts, render, skin, ridge=False)  # the template's chin is the kit's, not a terminator
    source = ["template"] * N_POINTS
    for i, (k, src) in anchors.items():
        vx[i], pts[i], source[i] = k, render.xy[k], src
    _outline(pts, vx, source, render.xy, skin)
    _lips(pts, vx, source, cues)
    return pts, vx, source


#: Upper and lower lip points of the 68-point layout (outer 49-53 / 55-59, inner 61-63 / 65-67), inner corners.
UPPER_LIP_68 = (49, 50, 51, 52, 53, 61, 62, 63)
LOWER_LIP_68 = (55, 56, 57, 58, 59, 65, 66, 67)
INNER_CORNERS_68 = (60, 64)


def _opened(render: FaceRender, vertices, deltas, jaw) -> np.ndarray | None:
    """Every vertex in the picture moved by the jaw-open slider (of *jaw*, indices) that moves it most; (N, 2).

    The lips part: the upper one goes up the picture or less down than the lower one. None without jaw-open.
    """
    if not jaw:
        return None
    d = np.asarray(deltas, np.float64)[np.asarray(jaw)]
    strongest = np.argmax((d ** 2).sum(2), axis=0)
    moved = np.asarray(vertices, np.float64) + d[strongest, np.arange(d.shape[1])]
    return render.view.project(moved)[1]


def _lip_pools(xy, cand, jaw, opened, a, b):
    """The lips the jaw-open parts between mouth corners *a* and *b* (pixels): (upper ids, lower ids) or None.

    The lips are the candidate vertices within the mouth's box (the corners'
    span and 10 % beyond, half its width above and below) that jaw-open moves
    at least :data:`EYE_SHARE` as much as its most moved one there; the upper
    lip those it moves up the picture or least down (at or above the midpoint
    of their vertical motions), the lower lip the others.
    """
    width = max(np.linalg.norm(b - a), 1.0)
    box = cand & (xy[:, 0] > min(a[0], b[0]) - 0.1 * width) & (xy[:, 0] < max(a[0], b[0]) + 0.1 * width) \
        & (np.abs(xy[:, 1] - (a[1] + b[1]) / 2) < 0.5 * width)
    if not box.any() or jaw[box].max() <= 0:
        return None
    lips = np.flatnonzero(box & (jaw >= EYE_SHARE * jaw[box].max()))
    dy = opened[lips, 1] - xy[lips, 1]  # down the picture when the mouth opens
    split = (dy.min() + dy.max()) / 2
    return lips[dy <= split], lips[dy > split]


def _nearest(pool, xy, p) -> int:
    return int(pool[np.argmin(np.linalg.norm(xy[pool] - p, axis=1))])


def _lips(pts, vx, source, cues: _Cues) -> None:
    """Template lip points lifted onto a vertex no mouth slider moves, moved onto the lips the jaw-open opens.

    A stylised mouth is often a piece of its own laid on a static skin (the
    Godette VRM's: its closed lips one line of vertices that ``a`` parts): the
    template's lip points land on the skin around it, where neither jaw-open
    nor smile moves anything, and the fit would not see the mouth open. Such a
    point goes to the nearest vertex (in the picture) of its lip
    (:func:`_lip_pools`; the inner corners 60 and 64 of either lip). Points
    already on a vertex a mouth slider moves (the ICT FaceKit's) are kept.
    """
    jaw, smile = cues.motion["jaw"], cues.motion["smile"]
    if jaw is None or cues.opened is None or source[48] != "sliders:smile" or source[54] != "sliders:smile":
        return
    pools = _lip_pools(cues.xy, cues.cand, jaw, cues.opened, cues.xy[vx[48]], cues.xy[vx[54]])
    if pools is None:
        return
    moving = jaw + (smile if smile is not None else 0.0)
    for ids, pool in zip((UPPER_LIP_68, LOWER_LIP_68, INNER_CORNERS_68), (*pools, np.concatenate(pools))):
        for i in ids:
            if len(pool) and source[i] == "template" and moving[vx[i]] <= 0:
                k = _nearest(pool, cues.xy, pts[i])
                vx[i], pts[i], source[i] = k, cues.xy[k], "sliders:jaw"


#: Inner-lip pairs of the 68-point layout (upper, lower).
INNER_LIP_PAIRS_68 = ((61, 67), (62, 66), (63, 65))


def part_closed_lips(vx, points, render: FaceRender, skin, vertices, deltas, names) -> np.ndarray:
    """Inner-lip points of a closed mouth lifted apart: the upper one onto the upper lip, the lower onto the lower.

    On a closed mouth the detector puts each upper inner-lip point and its
    lower partner (61/67, 62/66, 63/65) on the lips' one line, and the nearest
    vertex is one lip's for both, or each lands on the other's lip: the fit
    then cannot see the mouth open there, or twists the mouth to open it (the
    VALID head: 62 and 66 on one upper-lip vertex, or 63 on the lower lip and
    65 on the upper; the ICT FaceKit as a GLB: 61/67 and 62/66 on lower-lip
    vertices). For a pair whose lower vertex the jaw-open (below) does not move
    down the picture by a pixel more than its upper one, the visible
    skin vertices within :data:`LIP_RADIUS` inter-ocular distances of the two
    points are split by how far the jaw-open sliders (by name,
    :data:`SLIDER_PATTERNS`; each vertex by the one that moves it most) move
    them down the picture, at the midpoint of that motion's range: the upper
    point goes to the nearest vertex (in the picture) of those that move less
    (the upper lip), the lower point to the nearest of the others. Pairs the
    jaw-open parts, and rigs without a jaw-open slider, are kept.

    Parameters
    ----------
    vx : ndarray (68,), int
        The lifted map; a copy is returned.
    points : ndarray (68, 2)
        The detected points (pixels of *render*).
    render : FaceRender
    skin : ndarray (N,), bool
    vertices : ndarray (N, 3)
    deltas : ndarray (n, N, 3)
    names : sequence of str

    Returns
    -------
    ndarray (68,), int64
    """
    vx = np.array(vx, np.int64)
    opened = _opened(render, vertices, deltas, slider_groups(names)["jaw"])
    if opened is None:
        return vx
    drop = opened[:, 1] - render.xy[:, 1]  # down the picture when the mouth opens
    # a pair on one vertex, or whose lower point the jaw-open does not move down a pixel more than the upper
    shared = [(u, lo) for u, lo in INNER_LIP_PAIRS_68 if vx[u] == vx[lo] or drop[vx[lo]] - drop[vx[u]] < 1.0]
    P = np.asarray(points, np.float64)
    iod = np.linalg.norm(P[45] - P[36])
    ids = np.flatnonzero(skin)
    for u, lo in shared:
        near = ids[np.linalg.norm(render.xy[ids] - (P[u] + P[lo]) / 2, axis=1) < LIP_RADIUS * iod]
        if len(near) < 2:
            continue
        dy = drop[near]
        if dy.max() - dy.min() < 1.0:  # the jaw-open does not part them here (a pixel)
            continue
        split = (dy.min() + dy.max()) / 2
        vx[u], vx[lo] = _nearest(near[dy <= split], render.xy, P[u]), _nearest(near[dy > split], render.xy, P[lo])
    return vx


#: Radius (inter-ocular distances, in the picture) around a closed inner-lip pair in which its lips are looked for.
LIP_RADIUS = 0.05


def _check_chin(anchors, xy) -> None:
    """Drop a chin anchor that is not below the mouth by a fifth of its width (a jaw-open that moves only the lips)."""
    if 8 in anchors and 48 in anchors and 54 in anchors:
        a, b, c = xy[anchors[48][0]], xy[anchors[54][0]], xy[anchors[8][0]]
        if c[1] - (a[1] + b[1]) / 2 < 0.2 * np.linalg.norm(b - a):
            del anchors[8]


def _place_template(anchors, xy, skin):
    """The template (68, 2) fitted to the *anchors* ({landmark: (vertex, source)}) in the image.

    One affine map for the whole face, and the mouth's points (48-67) by the
    similarity that takes the template's mouth corners to the anchored ones
    (a stylised face's mouth is not where a human face's is, relative to its eyes).
    """
    if len(anchors) >= 2:
        ids = sorted(anchors)
        M = _affine(TEMPLATE_68[ids], xy[[anchors[i][0] for i in ids]])
    else:  # nothing to anchor on: the template on the skin's box
        M = np.array([[0.45 * np.ptp(xy[skin, 0]), 0.0], [0.0, 0.45 * np.ptp(xy[skin, 0])], xy[skin].mean(0)])
    pts = np.c_[TEMPLATE_68, np.ones(N_POINTS)] @ M
    if 48 in anchors and 54 in anchors:
        mouth = list(range(48, 68))
        pts[mouth] = _similarity(TEMPLATE_68[[48, 54]], xy[[anchors[48][0], anchors[54][0]]], TEMPLATE_68[mouth])
    return pts


def _similarity(src, dst, points):
    """*points* (P, 2) moved by the 2D similarity that takes the segment *src* (2, 2) to *dst* (2, 2)."""
    s0, s1 = src[1] - src[0], dst[1] - dst[0]
    z = complex(*s1) / complex(*s0) if np.any(s0) else 1.0
    q = (points[:, 0] - src[0, 0]) + 1j * (points[:, 1] - src[0, 1])
    w = q * z
    return np.c_[w.real + dst[0, 0], w.imag + dst[0, 1]]


def _outline(pts, vx, source, xy, skin) -> None:
    """Template jaw points 0-4 and 12-16 moved along their row to the face's outline (the outermost skin vertex)."""
    iod = max(np.linalg.norm(pts[45] - pts[36]), 1.0)
    for i in (*range(0, 5), *range(12, 17)):
        if source[i] != "template":
            continue
        side = -1 if i < 8 else 1
        row = np.flatnonzero(skin & (np.abs(xy[:, 1] - pts[i, 1]) < 0.03 * iod) & ((xy[:, 0] - pts[8, 0]) * side > 0))
        if len(row):
            k = row[np.argmax(xy[row, 0] * side)]
            vx[i], pts[i], source[i] = k, xy[k], "outline"


def _brows(anchors, cues: _Cues, guess) -> None:
    """Brow points 17-26: where the brow shapes move most in the column of the template's guess, above the eyes."""
    m = cues.motion["brow"]
    if m is None:
        return
    xy = cues.xy
    eye_y = guess[36:48, 1].min()
    iod = max(np.linalg.norm(guess[45] - guess[36]), 1.0)
    for i in range(17, 27):
        band = np.flatnonzero(cues.cand & (np.abs(xy[:, 0] - guess[i, 0]) < 0.06 * iod) & (xy[:, 1] < eye_y)
                              & (xy[:, 1] > eye_y - 0.8 * iod))
        if len(band) and m[band].max() > 0:
            anchors[i] = (band[np.argmax(m[band])], "sliders:brow")


# --------------------------------------------------------------------------- corrections and quality


def correct(lmap: LandmarkMap, vertex_fixes=None, pixel_fixes=None) -> LandmarkMap:
    """*lmap* with points set by hand: ``{landmark: vertex}`` and ``{landmark: (x, y)}`` in its render's pixels.

    A pixel is lifted like a detected point (:func:`lift`); a vertex is used
    as given and its point moved to its projection. Their source becomes ``user``.
    """
    vx, pts, src = lmap.vertices.copy(), lmap.points.copy(), list(lmap.source)
    n = len(lmap.render.xy)
    for i, v in (vertex_fixes or {}).items():
        if not 0 <= i < N_POINTS or not 0 <= v < n:
            raise ParameterError(f"correction: landmark {i} -> vertex {v}: landmarks are 0-67, vertices 0-{n - 1}")
        vx[i], pts[i], src[i] = v, lmap.render.xy[v], "user"
    for i, p in (pixel_fixes or {}).items():
        if not 0 <= i < N_POINTS:
            raise ParameterError(f"correction: landmark {i}: landmarks are 0-67")
        pts[i], src[i] = p, "user"
        vx[i] = lift(np.asarray(p, np.float64)[None], lmap.render, lmap.skin)[0]
    return LandmarkMap(vx, pts, src, lmap.render, lmap.skin, lmap.found_by, lmap.tried)


def points_from_sheet(xy) -> np.ndarray:
    """Pixels of the contact sheet (:func:`draw_sheet`) to pixels of its render; (P, 2) -> (P, 2)."""
    return (np.asarray(xy, np.float64) - (SHEET_SCALE - 1) / 2) / SHEET_SCALE


def map_quality(vertices, vx, *, yaw: float = 0.0, source=None) -> dict:
    """How plausible a 68-point map is on the neutral.

    Parameters
    ----------
    vertices : ndarray (N, 3)
        The neutral.
    vx : ndarray (68,), int
        The map.
    yaw : float
        Degrees that turn the face to +z (as the camera's yaw): symmetry is measured across the
        face's vertical mid-plane in that frame.
    source : list of str, optional
        Each point's source (:attr:`LandmarkMap.source`), counted per region.

    Returns
    -------
    dict
        ``iod``: inter-ocular distance (outer eye corners 36-45, rig units);
        ``symmetry_mean``, ``symmetry_max``: distance of each mirror pair's
        point from the mirror image of its partner, in inter-ocular distances
        (mid-plane through the pairs' mean midpoint); ``worst_pair``;
        ``regions``: per region, points by source (or the count without
        *source*); ``shared``: lists of landmarks that share one vertex.
    """
    V = np.asarray(vertices, np.float64)
    vx = np.asarray(vx, np.int64)
    if vx.shape != (N_POINTS,):
        raise ShapeError(f"map: expected {N_POINTS} vertex ids, got shape {vx.shape}")
    a = np.radians(yaw)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    P = V[vx] @ R.T
    iod = float(np.linalg.norm(P[45] - P[36]))
    left = np.array([p for p, _ in MIRROR_68])
    right = np.array([q for _, q in MIRROR_68])
    mid = float(np.mean((P[left, 0] + P[right, 0]) / 2))
    mirrored = P[right].copy()
    mirrored[:, 0] = 2 * mid - mirrored[:, 0]
    err = np.linalg.norm(P[left] - mirrored, axis=1) / max(iod, 1e-12)
    w = int(np.argmax(err))
    by_vertex: dict[int, list] = {}
    for i, v in enumerate(vx.tolist()):
        by_vertex.setdefault(v, []).append(i)
    if source is None:
        regions = {k: len(v) for k, v in REGIONS_68.items()}
    else:
        regions = {}
        for k, ids in REGIONS_68.items():
            regions[k] = {}
            for i in ids:
                regions[k][source[i]] = regions[k].get(source[i], 0) + 1
    return {"iod": iod, "symmetry_mean": float(err.mean()), "symmetry_max": float(err.max()),
            "worst_pair": MIRROR_68[w], "regions": regions,
            "shared": [ids for ids in by_vertex.values() if len(ids) > 1]}


#: Sheet colours (BGR) of each source of a point.
SOURCE_COLORS = {"detector": (60, 200, 60), "detector:brow height": (60, 200, 160), "user": (255, 140, 40), "template": (40, 40, 230), "outline": (40, 40, 230)}
_SLIDER_COLOR = (0, 170, 255)
#: The contact sheet is the render at this scale (``--points`` pixels are the sheet's).
SHEET_SCALE = 2


def draw_sheet(lmap: LandmarkMap, title: str = "") -> np.ndarray:
    """The render with the 68 numbered points drawn on it, at :data:`SHEET_SCALE`; (H, W, 3) uint8 BGR.

    Each point is drawn where its vertex projects, coloured by its source
    (detector green, brows raised teal, sliders orange, template/outline red, user blue), its
    number beside it; a line at the top says how the map was found.
    """
    import cv2

    k = SHEET_SCALE
    img = cv2.resize(lmap.render.image, None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
    xy = lmap.render.xy[lmap.vertices] * k + (k - 1) / 2
    for i, (p, src) in enumerate(zip(xy, lmap.source)):
        c = SOURCE_COLORS.get(src, _SLIDER_COLOR)
        q = (int(round(p[0])), int(round(p[1])))
        cv2.circle(img, q, 3, c, -1, cv2.LINE_AA)
        cv2.putText(img, str(i), (q[0] + 4, q[1] - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 2, cv2.LINE_AA)
        cv2.putText(img, str(i), (q[0] + 4, q[1] - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.38, c, 1, cv2.LINE_AA)
    counts = {}
    for src in lmap.source:
        counts[src] = counts.get(src, 0) + 1
    line = (title + "  " if title else "") + ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    cv2.rectangle(img, (0, 0), (img.shape[1], 20), (0, 0, 0), -1)
    cv2.putText(img, line, (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def map_distance(vertices, vx, reference) -> tuple[float, float]:
    """Mean and max distance between two maps' vertices, in inter-ocular distances of *reference*."""
    V = np.asarray(vertices, np.float64)
    a, b = V[np.asarray(vx)], V[np.asarray(reference)]
    d = np.linalg.norm(a - b, axis=1) / np.linalg.norm(b[45] - b[36])
    return float(d.mean()), float(d.max())


__all__ = ["MIRROR_68", "N_POINTS", "REGIONS_68", "STYLES", "TEMPLATE_68", "FaceRender", "LandmarkMap",
           "RenderStyle", "SHEET_SCALE", "BROW_HEIGHT_68", "correct", "detect_face", "draw_sheet", "points_from_sheet", "face_region", "find_landmark_map", "front_yaw", "lift",
           "lift_landmarks", "part_closed_lips", "raise_brows", "smooth_jaw", "chin_ridge", "surface_curvature",
           "map_distance", "map_quality", "motion_weights", "render_face", "skin_vertices", "slider_landmarks"]

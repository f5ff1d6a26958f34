"""Reading a UsdSkel export back with pxr's own queries (shared by tests/unit and tests/e2e)."""

import numpy as np


def usd_blendshape_frames(path):
    """(names, weights (T, M), meshes (T, N, 3)) by UsdSkel's own queries: AnimQuery weights, BlendShapeQuery points."""
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    cache.Populate(root, Usd.PrimDefaultPredicate)
    (binding,) = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
    skel_query = cache.GetSkelQuery(binding.GetSkeleton())
    anim = skel_query.GetAnimQuery()
    (skinning,) = binding.GetSkinningTargets()
    mesh = UsdGeom.Mesh(skinning.GetPrim())
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh.GetPrim()))
    point_ids = shapes.ComputeBlendShapePointIndices()
    offsets = shapes.ComputeSubShapePointOffsets()
    names, W, X = list(anim.GetBlendShapeOrder()), [], []
    for t in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
        w = anim.ComputeBlendShapeWeights(Usd.TimeCode(t))
        W.append(np.array(w))
        w_mesh = skinning.GetBlendShapeMapper().Remap(w)
        sub, bs_idx, sub_idx = shapes.ComputeSubShapeWeights(w_mesh)
        pts = mesh.GetPointsAttr().Get(Usd.TimeCode(t))
        shapes.ComputeDeformedPoints(sub, bs_idx, sub_idx, point_ids, offsets, pts)
        xforms = skel_query.ComputeSkinningTransforms(Usd.TimeCode(t))
        skinning.ComputeSkinnedPoints(xforms, pts, Usd.TimeCode(t))
        X.append(np.array(pts, dtype=np.float64))
    return stage, names, np.array(W), np.array(X)

"""Face regions: named groups of landmarks, each with its own key shapes (presets of the 68-point layout)."""

from __future__ import annotations

from .._validate import check_name
from ..errors import InputError

#: Default regions of the 68-point layout (the synthetic take's config uses the same lists).
REGION_PRESETS_68 = {
    "brows-eyes": list(range(17, 27)) + list(range(36, 48)),
    "mouth": list(range(3, 14)) + list(range(48, 68)),
    "face": "all",
}


def region_specs(regions, n_points: int, k: int | None = None) -> dict[str, tuple[list[int], int | None]]:
    """Resolve region definitions to ``{name: (landmark ids, k)}``.

    A region is ``"all"``, a list of landmark ids, ``null`` (a preset of the
    68-point layout: ``brows-eyes``, ``mouth``, ``face``) or a mapping
    ``{points: ..., k: ...}`` where either key may be left out (preset points,
    the stage's k).
    """
    regions = regions or {"face": "all"}
    out = {}
    for name, spec in regions.items():
        check_name(name, "regions")
        rk = k
        if isinstance(spec, dict):
            bad = sorted(set(spec) - {"points", "k"})
            if bad:
                raise InputError(f"regions: {name!r} has unknown key {bad[0]!r}; expected 'points' and/or 'k'")
            rk = spec.get("k", k)
            if isinstance(rk, bool) or not isinstance(rk, int) or rk < 1:
                raise InputError(f"regions: {name!r} k must be an integer >= 1, got {rk!r}")
            spec = spec.get("points")
        if spec is None:
            if name not in REGION_PRESETS_68:
                raise InputError(f"regions: {name!r} needs 'points' (presets: {', '.join(REGION_PRESETS_68)})")
            if n_points != 68 and REGION_PRESETS_68[name] != "all":
                raise InputError(f"regions: preset {name!r} is for the 68-point layout but the take has {n_points} points; "
                                 "give its landmark ids")
            spec = REGION_PRESETS_68[name]
        if spec == "all":
            out[name] = (list(range(n_points)), rk)
            continue
        if not isinstance(spec, list) or not spec or not all(isinstance(i, int) and not isinstance(i, bool) for i in spec):
            raise InputError(f"regions: {name!r} must be 'all', a list of landmark indices or {{points, k}}")
        bad = [i for i in spec if not 0 <= i < n_points]
        if bad:
            raise InputError(f"regions: {name!r} names landmark {bad[0]} but the take has {n_points} (0..{n_points - 1})")
        out[name] = (list(spec), rk)
    return out


def region_points(regions, n_points: int) -> dict[str, list[int]]:
    """Resolve region definitions (``"all"`` or index lists) to index lists."""
    return {name: pts for name, (pts, _) in region_specs(regions, n_points).items()}

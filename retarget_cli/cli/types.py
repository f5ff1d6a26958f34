"""Click parameter types for the value syntaxes of the command line: sizes, index lists, frames, regions, masks, vectors."""

from __future__ import annotations

import click


class Size(click.ParamType):
    """``WxH`` (or ``N`` for N x N when *square* is allowed) to ``(width, height)``, each in [lo, hi]."""

    name = "WxH"

    def __init__(self, *, square: bool = False, lo: int = 1, hi: int = 1 << 16, example: str = "320x320"):
        self.square, self.lo, self.hi, self.example = square, lo, hi, example

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        text = str(value).strip().lower()
        try:
            parts = [int(v) for v in text.split("x")]
            if len(parts) == 1 and self.square:
                parts = parts * 2
            if len(parts) != 2:
                raise ValueError
        except ValueError:
            self.fail(f"expected WxH{' or N' if self.square else ''} such as {self.example}, got {value!r}",
                      param, ctx)
        if not all(self.lo <= v <= self.hi for v in parts):
            self.fail(f"width and height must lie in [{self.lo}, {self.hi}], got {value}", param, ctx)
        return tuple(parts)


def index_ranges(text: str) -> list[int]:
    """``27-31,33`` (inclusive ranges, comma-separated) to a list of ints; ValueError on anything else."""
    out = []
    for part in text.replace(" ", "").split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


class IndexList(click.ParamType):
    """``27-31,33,35`` (inclusive ranges) to a list of landmark indices."""

    name = "SPEC"

    def convert(self, value, param, ctx):
        if isinstance(value, list):
            return value
        try:
            return index_ranges(str(value))
        except ValueError:
            self.fail(f"expected indices such as 27-31,36,39, got {value!r}", param, ctx)


class FrameList(click.ParamType):
    """``0,120,240`` or inclusive ranges ``a-b`` with an optional step ``a-b:s`` to a list of frame numbers."""

    name = "LIST"

    def convert(self, value, param, ctx):
        if isinstance(value, list):
            return value
        out = []
        for tok in str(value).replace(" ", "").split(","):
            if not tok:
                continue
            try:
                if "-" in tok:
                    rng, _, st = tok.partition(":")
                    a, b = (int(v) for v in rng.split("-"))
                    out += list(range(a, b + 1, int(st) if st else 1))
                else:
                    out.append(int(tok))
            except ValueError:
                self.fail(f"expected frame numbers such as 0,120 or 0-300:60, got {tok!r}", param, ctx)
        if not out:
            self.fail("give at least one frame", param, ctx)
        return out


class RegionSpec(click.ParamType):
    """``NAME``, ``NAME=all`` or ``NAME=a-b,c,...`` (inclusive ranges), each optionally ``:K``, to (name, spec).

    The spec is None (a preset by name), ``"all"``, a list of landmark ids, or ``{"points": ..., "k": K}``.
    """

    name = "NAME[=SPEC][:K]"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        spec = str(value)
        head, colon, kk = spec.rpartition(":") if ":" in spec else (spec, "", "")
        name, sep, body = head.partition("=")
        try:
            if not name or (sep and not body):
                raise ValueError
            k = int(kk) if colon else None
            if k is not None and k < 1:
                raise ValueError
            if not sep:
                pts = None
            elif body == "all":
                pts = "all"
            else:
                pts = index_ranges(body)
        except ValueError:
            self.fail(f"expected NAME, NAME=all or NAME=a-b,c,... optionally followed by :K, got {spec!r}", param, ctx)
        return name, (pts if k is None else {"points": pts, "k": k})


class MaskSpec(click.ParamType):
    """``REGION=FILE`` to (region, file)."""

    name = "REGION=FILE"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        region, sep, path = str(value).partition("=")
        if not sep or not region or not path:
            self.fail(f"expected REGION=FILE, got {value!r}", param, ctx)
        return region, path


class NumberOrWord(click.ParamType):
    """A number in a range, or one of *words* (``auto``): ``neutral_frame``."""

    def __init__(self, number: click.ParamType, words):
        self.number, self.words = number, tuple(words)
        self.name = f"{number.name}|{'|'.join(self.words)}"

    def convert(self, value, param, ctx):
        if isinstance(value, str) and value.strip().lower() in self.words:
            return value.strip().lower()
        try:
            return self.number.convert(value, param, ctx)
        except click.BadParameter:
            describe = getattr(self.number, "_describe_range", None)  # click's IntRange/FloatRange: "x>=0"
            what = f"a number ({describe()})" if describe else "a number"
            self.fail(f"expected {' or '.join(self.words)} or {what}, got {value!r}", param, ctx)


class Vector3(click.ParamType):
    """``X,Y,Z`` to a list of three floats."""

    name = "X,Y,Z"

    def convert(self, value, param, ctx):
        if isinstance(value, list):
            return value
        try:
            out = [float(v) for v in str(value).split(",")]
            if len(out) != 3:
                raise ValueError
        except ValueError:
            self.fail(f"expected X,Y,Z, got {value!r}", param, ctx)
        return out


#: The value syntaxes a :class:`~retarget_cli.config.Flag` may name (``Flag.value``); ``text``: a plain string
#: the command itself reads (a list of exports, a name pattern), whatever the Param's type.
VALUE_TYPES = {"size": Size, "indices": IndexList, "frames": FrameList, "region": RegionSpec, "mask": MaskSpec,
               "xyz": Vector3, "text": lambda: click.STRING}

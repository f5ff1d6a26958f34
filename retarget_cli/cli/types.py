"""Click parameter types shared by the commands: an image size and a list of landmark indices."""

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


class IndexList(click.ParamType):
    """``27-31,33,35`` (inclusive ranges) to a list of landmark indices."""

    name = "SPEC"

    def convert(self, value, param, ctx):
        if isinstance(value, list):
            return value
        out = []
        try:
            for part in str(value).replace(" ", "").split(","):
                lo, _, hi = part.partition("-")
                out += list(range(int(lo), int(hi or lo) + 1))
        except ValueError:
            self.fail(f"expected indices such as 27-31,36,39, got {value!r}", param, ctx)
        return out

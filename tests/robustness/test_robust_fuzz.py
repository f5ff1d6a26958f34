"""Fuzzed files into the readers (issue #17): only the tool's own errors (RetargetError) may escape.

A few hundred examples per reader by default; set RETARGET_FUZZ_EXAMPLES for more.
"""

from __future__ import annotations

import io
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from retarget_cli.errors import RetargetError

EXAMPLES = int(os.environ.get("RETARGET_FUZZ_EXAMPLES", "200"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _survives(read, name: str, data: bytes):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / name
        p.write_bytes(data)
        try:
            read(p)
        except RetargetError as exc:
            assert "\n" not in str(exc).strip(), str(exc)


_obj_line = st.one_of(
    st.builds(lambda *v: "v " + " ".join(v), *[st.sampled_from(["0", "1.5", "-2", "nan", "1e400", "x", ""])] * 3),
    st.builds(lambda *v: "f " + " ".join(v), *[st.sampled_from(["1", "2", "3", "0", "-1", "99999999", "1/1", "2//3",
                                                                "a"])] * 3),
    st.sampled_from(["vt 0 1", "vn 0 0 1", "# c", "mtllib x.mtl", "usemtl m", "o obj", "g grp", "s 1", ""]),
    st.text(max_size=20),
)


@FUZZ
@given(st.one_of(st.lists(_obj_line, max_size=30).map(lambda ls: "\n".join(ls).encode("utf-8", "replace")),
                 st.binary(max_size=300)))
def test_obj_reader(data):
    from retarget_cli.io.obj import count_vertices, read_obj

    _survives(read_obj, "m.obj", data)
    _survives(count_vertices, "m.obj", data)


_num = st.sampled_from(["1", "0", "-3", "2.5", "nan", "inf", "1e999", "300000000", "x", "", "99999999999999999999"])


@FUZZ
@given(st.one_of(
    st.builds(lambda n, body: f"version: 1\nn_points: {n}\n{{\n{body}\n}}\n".encode(), _num,
              st.lists(st.builds(lambda a, b: f"{a} {b}", _num, _num), max_size=8).map("\n".join)),
    st.binary(max_size=200)))
def test_pts_reader(data):
    from retarget_cli.io.annotations import read_annotations

    _survives(lambda p: read_annotations([p]), "face_00003.pts", data)


@FUZZ
@given(st.one_of(
    st.lists(st.lists(_num, min_size=0, max_size=5).map(",".join), max_size=8)
    .map(lambda rows: ("frame,point,x,y\n" + "\n".join(rows)).encode()),
    st.binary(max_size=200)))
def test_csv_reader(data):
    from retarget_cli.io.annotations import read_annotations

    _survives(lambda p: read_annotations([p]), "ann.csv", data)


_yaml_scalar = st.sampled_from(["1", "-1", ".nan", ".inf", "true", "null", "x", "[1, 2]", "{a: 1}", "'5'", "1e999",
                                "[*a]", "&a [1]", "!!python/object:os.system x", "''", "../x"])
_keys = st.sampled_from(["output_dir", "seed", "track", "select", "decompose", "pose", "apply", "5", "k", "video",
                         "regions", "alpha", "lost_fraction", "output", "csv", "masks", "rigid_points"])


@FUZZ
@given(st.one_of(
    st.lists(st.tuples(_keys, st.one_of(_yaml_scalar, st.lists(st.tuples(_keys, _yaml_scalar), max_size=4)
                                        .map(lambda kv: "\n" + "\n".join(f"  {k}: {v}" for k, v in kv)))),
             max_size=6).map(lambda kv: "\n".join(f"{k}: {v}" for k, v in kv).encode()),
    st.binary(max_size=200)))
def test_config_reader(data):
    from retarget_cli.config import load_config
    from retarget_cli.run.pipeline import stage_params

    _survives(lambda p: load_config(p, stage_params()), "config.yaml", data)


_dtypes = st.sampled_from(["<f4", "<f8", "<i8", "|b1", "<U3", "<M8[s]", "<c8", "<f2", "|u1"])
_shapes = st.lists(st.integers(0, 4), max_size=3).map(tuple)


def _npz_bytes(members) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, payload in members:
            zf.writestr(name + ".npy", payload)
    return buf.getvalue()


def _array_bytes(dtype, shape, fill) -> bytes:
    b = io.BytesIO()
    with np.errstate(invalid="ignore"):
        a = np.full(shape, fill).astype(dtype) if not dtype.startswith("<M") else np.zeros(shape, dtype)
    np.lib.format.write_array(b, a, allow_pickle=False)
    return b.getvalue()


_member = st.one_of(
    st.builds(_array_bytes, _dtypes, _shapes, st.sampled_from([0, 1, 2.5, -1, np.nan, np.inf])),
    st.binary(max_size=120),
    st.builds(lambda h: b"\x93NUMPY\x01\x00" + len(h).to_bytes(2, "little") + h, st.binary(max_size=80)),
)
_names = st.sampled_from(["points", "confidence", "head", "stabilized", "fps", "frame_size", "frames", "names",
                          "meta"])


@settings(FUZZ, max_examples=EXAMPLES)
@given(st.lists(st.tuples(_names, _member), max_size=6), st.sampled_from([0, 1, 2]))
def test_landmarks_reader(members, real_points):
    from retarget_cli.io.landmarks import load_landmarks

    if real_points:  # often a valid 'points', so that the other keys are reached
        members = [("points", _array_bytes("<f4", (3, 4, 2), 1.0 * real_points)), *members]
    _survives(load_landmarks, "lm.npz", _npz_bytes(dict(members).items()))

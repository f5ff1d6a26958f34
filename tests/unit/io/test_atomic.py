import numpy as np
import pytest

from retarget_cli.errors import RetargetError
from retarget_cli.io.atomic import atomic_open, check_not_input, load_npz, savez


def test_savez_is_byte_identical_and_loadable(tmp_path):
    arrays = {"a": np.arange(10.0), "names": np.array(["x", "y"]), "s": np.array("{}")}
    savez(tmp_path / "1.npz", arrays)
    savez(tmp_path / "2.npz", arrays)
    assert (tmp_path / "1.npz").read_bytes() == (tmp_path / "2.npz").read_bytes()
    back = load_npz(tmp_path / "1.npz")
    np.testing.assert_array_equal(back["a"], arrays["a"])
    assert back["names"].tolist() == ["x", "y"]


def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_open(p, "w") as fh:
            fh.write("half")
            raise RuntimeError("killed")
    assert p.read_text() == "old"
    assert list(tmp_path.iterdir()) == [p]


def test_output_may_not_overwrite_an_input(tmp_path):
    with pytest.raises(RetargetError, match="overwrite the input"):
        check_not_input(tmp_path / "a" / ".." / "x.npz", [tmp_path / "x.npz"])


def test_load_npz_names_the_file(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(RetargetError, match="bad.npz: not an .npz"):
        load_npz(bad)

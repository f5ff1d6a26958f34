"""targets.yaml: the rig's every-frame curves (``curves:``, written by ``auto-pose --frames all``)."""

import numpy as np
import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.stagefiles import read_keys, read_targets, write_keys, write_targets


def test_targets_yaml_names_every_frames_curves_beside_the_key_sliders(tmp_path):
    regions = {"mouth": {"keys": {0: "mouth/key_00000.obj"}, "vertices": None, "sliders": ["jawOpen"]}}
    write_targets(tmp_path / "targets.yaml", regions, rig="rig.yaml", sliders="sliders.csv", curves="curves.csv")
    tg = read_targets(tmp_path / "targets.yaml")
    assert tg.curves == tmp_path / "curves.csv" and tg.sliders == tmp_path / "sliders.csv"
    write_targets(tmp_path / "keys.yaml", regions, rig="rig.yaml", sliders="sliders.csv")
    assert read_targets(tmp_path / "keys.yaml").curves is None
    assert "curves" not in (tmp_path / "keys.yaml").read_text()


def test_curves_without_a_rig_is_a_one_line_error(tmp_path):
    (tmp_path / "targets.yaml").write_text("curves: curves.csv\nregions:\n  face:\n    keys: {0: k.obj}\n")
    with pytest.raises(InputError, match="'curves' .* needs 'rig' and 'sliders'"):
        read_targets(tmp_path / "targets.yaml")


def test_key_rows_are_found_from_the_source_frames(tmp_path):
    """keys.json names keys by source frame; their rows come from the landmarks' frames (#34), whatever `rows`
    the file holds (a key list edited by hand keeps stale ones)."""
    path = tmp_path / "keys.json"
    write_keys(path, tmp_path / "landmarks.npz",
               {"mouth": {"points": [0, 1], "method": "manual", "frames": [104, 110], "rows": [9, 9, 9], "error": 0}},
               {"frame": 110, "row": 0, "source": "given", "reason": "test"})
    kf = read_keys(path)
    source = np.arange(100, 140, 2)  # a take tracked with start: 100, step: 2
    kf.resolve_rows(source, "landmarks.npz")
    assert kf.regions["mouth"]["rows"] == [2, 5] and kf.neutral["row"] == 5
    kf.regions["mouth"]["frames"] = [104, 105]
    with pytest.raises(InputError, match=r"region 'mouth' key frame 105 is outside the take \(20 frames in "
                                         r"landmarks.npz, source frames 100-138\)"):
        kf.resolve_rows(source, "landmarks.npz")

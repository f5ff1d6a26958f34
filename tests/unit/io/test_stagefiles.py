"""targets.yaml: the rig's every-frame curves (``curves:``, written by ``auto-pose --frames all``)."""

import pytest

from retarget_cli.errors import InputError
from retarget_cli.io.stagefiles import read_targets, write_targets


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

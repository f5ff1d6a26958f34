"""The ICT FaceKit as USD: written by the `apply --format usd` writer (UsdSkel blend shapes), read back as a rig
through rig.yaml `source:` with the kit's shipped `landmarks:`, `exclusive:` and `names:`. The rig evaluates as
the OBJ rig does.

Uses sample_data/ict (MIT) through the `ict_rig_dir` fixture.
"""

import numpy as np
import pytest
import yaml

from retarget_cli.io.exports import rig_shapes, write_usd
from retarget_cli.io.rig import load_rig

pytest.importorskip("pxr", reason="usd-core (the 'usd' extra) is not installed")


def test_ict_through_usd_evaluates_as_the_obj_rig(ict_rig_dir, tmp_path):
    ict = load_rig(ict_rig_dir / "rig.yaml")
    d = tmp_path / "usd"
    d.mkdir()
    write_usd(d / "ict.usd", ict.template, ict.neutral, None, 1, 30.0,
              morph_targets=lambda: rig_shapes(ict, np.zeros((1, ict.n_sliders))))
    shipped = yaml.safe_load((ict_rig_dir / "rig.yaml").read_text())
    (d / "rig.yaml").write_text(yaml.safe_dump({"source": "ict.usd",
                                                **{k: shipped[k] for k in ("range", "landmarks", "exclusive",
                                                                           "names")}}))
    usd = load_rig(d / "rig.yaml")
    assert usd.names == ict.names and usd.n_vertices == ict.n_vertices  # USD keeps the OBJ's vertices, in order
    np.testing.assert_allclose(usd.neutral, ict.neutral, rtol=0, atol=1e-5)  # float32 in the file, cm
    for w in np.random.default_rng(0).uniform(0, 1, (3, ict.n_sliders)):
        np.testing.assert_allclose(usd.evaluate(w), ict.evaluate(w), rtol=0, atol=1e-5)
    assert usd.landmarks[1].tolist() == shipped["landmarks"]
    assert np.array_equal(usd.lower, ict.lower) and np.array_equal(usd.upper, ict.upper)

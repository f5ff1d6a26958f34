"""Whether the tests of the pretrained detector (the extra 'detect') run (shared by tests/unit and tests/cli).

They skip where the extra is not installed, except under ``RETARGET_REQUIRE_DETECTOR=1`` (set by ``make test``,
which installs it, and so by ``.ci/run``): there they run, and fail if the detector cannot load its model.
"""

import os

import pytest

from retarget_cli.methods.tracking.detect import detector_installed

#: The detector's tests must run: a detector that cannot load its model fails them instead of skipping them.
REQUIRED = os.environ.get("RETARGET_REQUIRE_DETECTOR", "") not in ("", "0")

needs_detector = pytest.mark.skipif(not REQUIRED and not detector_installed(),
                                    reason="needs the optional extra 'detect' (dlib-bin, face_recognition_models): "
                                           "pip install -e '.[detect]'")

"""dlib's frontal face detector kept as a file in the user's cache, so that a run loads it in milliseconds.

``dlib.get_frontal_face_detector()`` rebuilds the HOG detector (Dalal & Triggs 2005) from a copy compiled
into dlib, which takes 1-3 s of CPU per process on this project's 2-core machines, more than the rest of
a short clip's start-up. The same detector saved in dlib's own binary format (``fhog_object_detector.save``,
155 KB) loads in about 10 ms and finds the same boxes with the same scores (checked on the shared clips, and by
``tests/unit/io/test_face_detector.py``).

:func:`face_detector_file` returns that file, ``detectors/frontal_face-dlib-<version>.svm`` in the user's cache
folder (:func:`~retarget_cli.io.rig.cache.user_cache_dir`: ``$RETARGET_CACHE_DIR``, else
``$XDG_CACHE_HOME/retarget``, else ``~/.cache/retarget``), writing it on first use: dlib saves it under a
temporary name in that folder and it is renamed into place (:mod:`retarget_cli.io.atomic`), so concurrent
workers see a whole file or none. With ``$RETARGET_CACHE_SIZE=0`` (the cache keeps nothing), or when the folder
cannot be written, there is no file and the detector is built from dlib's copy as before.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

from .atomic import guard_writes, write_bytes
from .rig.cache import cache_limit, user_cache_dir

log = logging.getLogger(__name__)

#: The folder of the detector's file inside the user's cache folder.
DETECTOR_FOLDER = "detectors"


def face_detector_file(environ=None) -> Path | None:
    """The frontal face detector of the installed dlib as a file in the user's cache (written on first use).

    Returns None when dlib is not installed, the cache keeps nothing (``$RETARGET_CACHE_SIZE=0``) or the file
    cannot be written (logged); the caller then builds the detector from dlib's own copy.

    Parameters
    ----------
    environ : mapping, optional
        The environment (default ``os.environ``).
    """
    try:
        import dlib
    except ImportError:
        return None
    if cache_limit(environ) == 0:
        return None
    folder = user_cache_dir(environ) / DETECTOR_FOLDER
    file = folder / f"frontal_face-dlib-{dlib.__version__}.svm"
    if file.is_file():
        return file
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder, prefix=".build-") as tmp:
            saved = Path(tmp) / file.name
            dlib.get_frontal_face_detector().save(str(saved))
            data = saved.read_bytes()
        with guard_writes(roots=[folder], label="the detector cache"):
            write_bytes(file, data)
    except (OSError, RuntimeError) as exc:
        log.warning("face detector cache %s not written (%s)", file, exc)
        return None
    log.info("face detector: cached in %s", file)
    return file


__all__ = ["face_detector_file", "DETECTOR_FOLDER"]

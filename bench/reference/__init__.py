"""The benchmarks' independent face reference: MediaPipe Face Mesh 0.10.14 in its own venv.

:func:`ensure_venv` creates ``build/bench-venv-mediapipe`` once (``python3.11 -m venv``, then pip
installs ``mediapipe==0.10.14`` and ``numpy<2`` from the package index); :func:`reference_landmarks`
runs ``mp_runner.py`` inside it on a video and caches ``build/reference/<stem>-<sha256[:12]>.npz``.
MediaPipe needs numpy < 2, so it never becomes a dependency of the project; nothing under
``retarget_cli`` or ``tests`` imports it. Run ``python bench/reference/__init__.py VIDEO...`` to
fill the cache by hand.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
VENV = ROOT / "build" / "bench-venv-mediapipe"
CACHE = ROOT / "build" / "reference"
RUNNER = Path(__file__).resolve().parent / "mp_runner.py"
REQUIREMENTS = ("mediapipe==0.10.14", "numpy<2")


class ReferenceUnavailable(RuntimeError):
    """The MediaPipe venv cannot be made here (no python3.11, no package index)."""


def venv_python(venv: Path = VENV) -> Path:
    return venv / "bin" / "python"


def ensure_venv(venv: Path = VENV, *, log=print) -> Path:
    """Create the MediaPipe venv once (idempotent: a stamp file records the installed requirements).

    Returns the venv's python. Raises :class:`ReferenceUnavailable` when it cannot be built.
    """
    stamp = venv / ".installed-stamp"
    want = "\n".join(REQUIREMENTS) + "\n"
    py = venv_python(venv)
    if stamp.is_file() and stamp.read_text() == want and py.exists():
        return py
    base = shutil.which("python3.11")
    if base is None:
        raise ReferenceUnavailable("python3.11 not found (the MediaPipe 0.10.14 wheels need CPython 3.8-3.12)")
    log(f"creating {venv} with {', '.join(REQUIREMENTS)} (once)")
    try:
        if not py.exists():
            subprocess.run([base, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *REQUIREMENTS],
                       check=True)
    except subprocess.CalledProcessError as exc:
        raise ReferenceUnavailable(f"could not build {venv}: {exc}") from exc
    stamp.write_text(want)
    return py


def sha256_file(path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def cache_path(video, cache: Path = CACHE) -> Path:
    """``build/reference/<stem>-<sha256[:12]>.npz`` for *video*."""
    video = Path(video)
    return cache / f"{video.stem}-{sha256_file(video)[:12]}.npz"


def reference_landmarks(video, *, cache: Path = CACHE, venv: Path = VENV, log=print) -> dict:
    """MediaPipe Face Mesh points of every frame of *video*, from the cache or computed once.

    Returns
    -------
    dict
        ``points`` float32 (T, 478, 2) image pixels (NaN where no face), ``found`` bool (T,),
        ``fps`` float, ``frame_size`` (2,) ``[width, height]``, ``path`` (the cache file).
    """
    out = cache_path(video, cache)
    if not out.is_file():
        py = ensure_venv(venv, log=log)
        log(f"MediaPipe Face Mesh on {video} -> {out}")
        subprocess.run([str(py), str(RUNNER), str(video), str(out)], check=True, stderr=subprocess.DEVNULL)
    with np.load(out) as d:
        return {"points": d["points"], "found": d["found"], "fps": float(d["fps"]),
                "frame_size": d["frame_size"], "path": out}


if __name__ == "__main__":
    for v in sys.argv[1:]:
        r = reference_landmarks(v)
        print(f"{r['path']}: {len(r['found'])} frames, face in {int(r['found'].sum())}")

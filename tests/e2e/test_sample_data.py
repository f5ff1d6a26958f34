"""The committed sample_data/ is exactly what `make sample` generates."""

from pathlib import Path

import numpy as np

from retarget_cli.io.video import VideoReader
from retarget_cli.synth import write_take

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"


def test_sample_data_is_reproducible(tmp_path):
    write_take(tmp_path, n_frames=240, size=(320, 320), seed=0)
    committed = sorted(p.relative_to(SAMPLE) for p in SAMPLE.rglob("*") if p.is_file())
    generated = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert committed == generated
    for rel in committed:
        if rel.suffix == ".mp4":
            continue  # the container embeds the encoder's version; compared by content below
        assert (SAMPLE / rel).read_bytes() == (tmp_path / rel).read_bytes(), f"{rel} differs: run `make sample`"
    with VideoReader(SAMPLE / "face.mp4") as a, VideoReader(tmp_path / "face.mp4") as b:
        diffs = [np.abs(x.astype(int) - y.astype(int)).mean() for x, y in zip(a, b)]
    assert len(diffs) == 240 and max(diffs) < 1.0

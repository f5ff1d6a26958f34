"""Kill-and-rerun (issue #17): SIGKILL `retarget run` at random moments, rerun: byte-identical outputs, no .part."""

from __future__ import annotations

import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from conftest import snapshot


def _outputs(out: Path) -> dict:
    """The run's outputs (not its manifests, caches or output manifests, which hold times)."""
    return {k: v for k, v in snapshot(out).items()
            if not k.startswith(".retarget/") and not Path(k).name.startswith(".retarget-")}


def test_sigkill_at_random_moments_then_rerun_gives_identical_outputs(tiny_run, tmp_path):
    take = tmp_path / "take"
    shutil.copytree(tiny_run, take)
    shutil.rmtree(take / "out")
    want = _outputs(tiny_run / "out")
    script = Path(sys.executable).parent / "retarget"
    cmd = [str(script)] if script.is_file() else [sys.executable, "-m", "retarget_cli"]
    rng = random.Random(17)
    for _ in range(2):
        proc = subprocess.Popen([*cmd, "-q", "run", str(take / "config.yaml"), "--force"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.3, 1.5))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        done = subprocess.run([*cmd, "-q", "run", str(take / "config.yaml")], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        assert _outputs(take / "out") == want
        assert not list(take.rglob("*.part*"))

"""`retarget batch`: 4 synthetic shots on Dask equal 4 separate `retarget run`s; worker death, failures, reruns."""

import hashlib
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.synth.take import write_take

pytest.importorskip("distributed", reason="needs the extra batch (dask[distributed])")

SHOTS = """\
output_dir: bout
base: t1/config.yaml
shots:
  - {name: a, config: t1/config.yaml, set: {select.k: 4}}
  - {name: b, config: t2/config.yaml, set: {select: {k: 3}}}
  - {name: c, set: {select.k: 3, seed: 2}}
  - name: d
    video: t2/face.mp4
    init: t2/face_00000.pts
    set: {select.k: 4, pose.rig: t2/rig.yaml, pose.poses: t2/truth.npz}
"""

#: The same four shots as plain runs: (config, --set ..., output folder relative to the tree).
REFERENCE = [
    ("t1/config.yaml", ["select.k=4"], "t1/out"),
    ("t2/config.yaml", ["select.k=3"], "t2/out"),
    ("t1/config.yaml", ["select.k=3", "seed=2"], "ref/c"),
    ("t1/config.yaml", ["select.k=4", "track.video=../t2/face.mp4", "track.init=../t2/face_00000.pts",
                        "pose.rig=../t2/rig.yaml", "pose.poses=../t2/truth.npz"], "ref/d"),
]


def tree(d: Path) -> dict:
    """Relative path to sha256 of every output file (manifests, caches and stale temporaries aside)."""
    return {p.relative_to(d).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file() and ".retarget" not in p.parts and not p.name.endswith(".part")}


def invoke(args):
    return CliRunner().invoke(main, args, catch_exceptions=False)


@pytest.fixture(scope="module")
def takes(small_take_template, tmp_path_factory):
    """Two 60-frame synthetic takes (t1, t2) and the shot list, plus reference outputs of plain runs."""
    root = tmp_path_factory.mktemp("batch")
    shutil.copytree(small_take_template, root / "t1")
    write_take(root / "t2", n_frames=60, size=(192, 192), seed=2)
    (root / "shots.yaml").write_text(SHOTS)
    ref = tmp_path_factory.mktemp("batch_ref")
    for name in ("t1", "t2"):
        shutil.copytree(root / name, ref / name)
    expected = {}
    for config, sets, out in REFERENCE:
        args = ["-q", "run", str(ref / config)] + [a for s in sets for a in ("--set", s)]
        if out.startswith("ref/"):
            args += ["--set", f"output_dir=../{out}"]
        r = invoke(args)
        assert r.exit_code == 0, r.output
        expected[out] = tree(ref / out)
        assert expected[out], out
    return root, expected


@pytest.fixture(scope="module")
def cluster():
    """A 2-worker LocalCluster reached through --scheduler (the existing-cluster path)."""
    from retarget_cli.batch.engine import local_cluster, quiet_dask

    quiet_dask()
    with local_cluster(2) as c, c.get_client() as client:
        yield c, client


@pytest.fixture(scope="module")
def batch_done(takes):
    root, expected = takes
    r = invoke(["batch", str(root / "shots.yaml"), "--jobs", "2"])
    assert r.exit_code == 0, r.output + r.stderr
    return root, expected, r


def test_batch_equals_separate_runs(batch_done):
    import json

    root, expected, r = batch_done
    got = {"t1/out": tree(root / "t1/out"), "t2/out": tree(root / "t2/out"),
           "ref/c": tree(root / "bout/c"), "ref/d": tree(root / "bout/d")}
    assert got == expected
    summary = json.loads((root / "bout/batch.json").read_text())
    assert [s["name"] for s in summary["shots"]] == ["a", "b", "c", "d"]
    assert all(s["status"] == "done" and s["frames"] == 60 for s in summary["shots"])
    assert all(set(s["stages"]) == {"track", "select", "decompose", "pose", "apply"} for s in summary["shots"])
    # The table on stdout has a row per shot; the index links every shot's folder.
    rows = [ln.split()[0] for ln in r.stdout.splitlines()[1:5]]
    assert rows == ["a", "b", "c", "d"]
    index = (root / "bout/index.html").read_text()
    assert 'href="c"' in index and 'href="../t1/out"' in index


def test_rerun_after_completion_runs_no_stage(batch_done, cluster):
    import json

    root, _, _ = batch_done
    r = invoke(["batch", str(root / "shots.yaml"), "--scheduler", cluster[0].scheduler_address])
    assert r.exit_code == 0, r.output
    shots = json.loads((root / "bout/batch.json").read_text())["shots"]
    assert len(shots) == 4
    assert all(st["status"] == "skipped" for s in shots for st in s["stages"].values()), shots
    # Nothing is pending, so nothing to emit.
    r = invoke(["batch", str(root / "shots.yaml"), "--emit-commands"])
    assert r.exit_code == 0 and r.stdout == ""


def test_killed_worker_and_broken_shot(takes, cluster):
    """A worker killed mid-shot: the shot reruns elsewhere with identical outputs; a broken shot fails alone."""
    import json

    root, expected = takes
    (root / "broken.mp4").write_bytes(b"\x00not a video" * 100)
    (root / "kill.yaml").write_text(
        "output_dir: kout\nbase: t1/config.yaml\nshots:\n"
        "  - {name: c, set: {select.k: 3, seed: 2}}\n"
        "  - {name: bad, video: broken.mp4}\n"
        "  - name: d\n    video: t2/face.mp4\n    init: t2/face_00000.pts\n"
        "    set: {select.k: 4, pose.rig: t2/rig.yaml, pose.poses: t2/truth.npz}\n")
    c, client = cluster
    pids = client.run(os.getpid)
    killed = {}

    def killer():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not killed:
            if any((root / "kout" / s / ".retarget" / "track.json").is_file() for s in ("c", "d")):
                for addr, keys in client.processing().items():
                    good = [k for k in keys if "-bad-" not in k]
                    if good and addr in pids:
                        os.kill(pids[addr], signal.SIGKILL)
                        killed[pids[addr]] = good
                        return
            time.sleep(0.01)

    t = threading.Thread(target=killer)
    t.start()
    r = invoke(["batch", str(root / "kill.yaml"), "--scheduler", c.scheduler_address, "--retries", "1"])
    t.join()
    assert killed, "no worker was killed while running a shot"
    assert r.exit_code == 1
    shots = {s["name"]: s for s in json.loads((root / "kout/batch.json").read_text())["shots"]}
    assert shots["c"]["status"] == shots["d"]["status"] == "done"
    assert shots["bad"]["status"] == "failed" and shots["bad"]["attempts"] == 2
    assert "broken.mp4" in shots["bad"]["error"]
    assert "broken.mp4" in r.stdout  # the error is in the table
    (pid, _), = killed.items()
    assert all(s["worker"].rsplit(":", 1)[1] != str(pid) for s in (shots["c"], shots["d"]))
    assert tree(root / "kout/c") == expected["ref/c"]
    assert tree(root / "kout/d") == expected["ref/d"]


def test_emitted_commands_run_by_a_shell(takes):
    root, expected = takes
    (root / "emit.yaml").write_text(SHOTS.replace("output_dir: bout", "output_dir: eout"))
    r = invoke(["batch", str(root / "emit.yaml"), "--emit-commands", "--only", "[!abc]"])
    assert r.exit_code == 0, r.output
    lines = r.stdout.splitlines()
    assert len(lines) == 1 and "--set output_dir=" in lines[0]
    assert shlex.split(lines[0])[:4] == [str(Path(sys.executable).absolute()), "-m", "retarget_cli", "run"]
    env = dict(os.environ, PATH="/usr/bin:/bin")  # no retarget on PATH, as on a farm host: the line still runs
    subprocess.run(["bash", "-e", "-c", r.stdout], check=True, env=env, cwd="/", capture_output=True)
    assert tree(root / "eout/d") == expected["ref/d"]
    assert not (root / "eout/c").exists()

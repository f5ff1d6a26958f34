"""What a run leaves behind (issue #17): temporary files, partial key sets, stale outputs; Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main


def _cli(*args):
    res = CliRunner().invoke(main, ["-q", *map(str, args)])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    return res


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _killed_run_journal(root: Path, *parts: Path, pid=None, start="?") -> Path:
    """What a SIGKILLed run leaves: its journal of temporary names (pid, start) and the files."""
    journal = root / f".retarget-parts-{pid or _dead_pid()}-0a1b2c3d.txt"
    journal.write_text(f"{pid or _dead_pid()} {start}\n" + "".join(p.relative_to(root).as_posix() + "\n" for p in parts))
    return journal


def test_stale_part_files_are_removed_by_the_next_run(take):
    out = take / "out"
    part = out / "frames" / ".frame_00006.obj.k3x9q0ab.part"  # a SIGKILLed run's temporary file, in its journal
    part.write_bytes(b"v 1 2")
    journal = _killed_run_journal(out, part)
    users = [out / "frames" / "notes.part", out / "frames" / ".mine.0a1b2c3d.part"]  # the user's, named alike
    for u in users:
        u.write_text("mine")
    res = _cli("run", take / "config.yaml")
    assert res.exit_code == 0, res.output
    assert not part.exists() and not journal.exists()
    assert all(u.read_text() == "mine" for u in users), "a file retarget did not write was deleted"


def test_stale_part_files_are_removed_by_a_single_command(take):
    out = take / "out" / "frames2"
    out.mkdir()
    part = out / ".animation.glb.0a1b2c3d.part"
    part.write_bytes(b"")
    _killed_run_journal(out, part)
    res = _cli("apply", take / "out/weights.npz", take / "out/targets/targets.yaml", "-o", out)
    assert res.exit_code == 0, res.output
    assert not part.exists() and (out / "frame_00000.obj").is_file()


def test_a_running_process_keeps_its_temporary_files(tmp_path):
    """A journal whose writer still runs (this process), or a pid now used by another process, is told apart."""
    from retarget_cli.io.atomic import _start_time, remove_stale_parts

    live = tmp_path / ".a.obj.0a1b2c3d.part"
    live.write_text("being written")
    _killed_run_journal(tmp_path, live, pid=os.getpid(), start=_start_time(os.getpid()))
    assert remove_stale_parts(tmp_path) == [] and live.exists()
    reused = tmp_path / "sub" / ".b.obj.0a1b2c3d.part"
    reused.parent.mkdir()
    reused.write_text("left by a killed run whose pid is now ours")
    (tmp_path / ".retarget-parts-1-0a1b2c3d.txt").write_text(f"{os.getpid()} 1\n" + "sub/.b.obj.0a1b2c3d.part\n")
    if _start_time(os.getpid()) != "?":
        assert remove_stale_parts(tmp_path) == [reused] and live.exists()


def test_a_second_run_into_the_same_folder_fails_at_once(take):
    """Two runs into one output_dir: the second stops with one line naming the folder and the first run."""
    first = subprocess.Popen([*_retarget(), "run", str(take / "config.yaml"), "--force"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    lock = take / "out" / ".retarget" / "lock"
    end = time.monotonic() + 60
    while time.monotonic() < end and first.poll() is None and f"pid {first.pid}" not in (
            lock.read_text() if lock.exists() else ""):
        time.sleep(0.01)
    second = subprocess.run([*_retarget(), "run", str(take / "config.yaml"), "--force"], capture_output=True,
                            text=True, timeout=120)
    first_err = first.communicate(timeout=120)[1]
    if first.returncode == 0 and f"pid {first.pid}" not in second.stderr:
        pytest.skip("the first run finished before the second started")
    assert first.returncode == 0, first_err
    assert second.returncode == 1, second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and "another retarget run is writing into this output_dir" in lines[0], lines
    assert f"pid {first.pid}" in lines[0] and str(take / "out") in lines[0]


def test_interrupt_right_after_the_temp_file_is_created_removes_it(tmp_path, monkeypatch):
    from retarget_cli.io.atomic import write_text

    real_open = os.open

    def open_then_interrupt(path, *a, **k):
        fd = real_open(path, *a, **k)
        if str(path).endswith(".part"):
            os.close(fd)
            raise KeyboardInterrupt
        return fd

    monkeypatch.setattr(os, "open", open_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_text(tmp_path / "x.txt", "data")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def _pose_args(take, keys, out):
    return ["pose-keys", keys, take / "rig.yaml", "--poses", take / "truth.npz",
            "--mask", f"brows-eyes={take / 'target/regions/brows-eyes.txt'}",
            "--mask", f"mouth={take / 'target/regions/mouth.txt'}", "-o", out]


def test_pose_keys_failing_midway_leaves_no_orphan_key_objs(take, monkeypatch):
    import retarget_cli.stages.pose as pose

    real, calls = pose.write_obj, []

    def fail_on_the_fifth(*a, **k):
        calls.append(1)
        if len(calls) == 5:
            raise OSError(28, "No space left on device", str(a[0]))
        return real(*a, **k)

    monkeypatch.setattr(pose, "write_obj", fail_on_the_fifth)
    out = take / "out" / "t2"
    res = _cli(*_pose_args(take, take / "out/keys.json", out))
    assert res.exit_code == 1 and "No space left" in res.stderr
    assert len(calls) == 5
    assert not list(out.rglob("*.obj")) and not (out / "targets.yaml").exists()


def test_rerun_with_other_keys_removes_the_old_keys_objs(take):
    import json

    out = take / "out" / "t2"
    assert _cli(*_pose_args(take, take / "out/keys.json", out)).exit_code == 0
    first = {p.relative_to(out).as_posix() for p in out.rglob("*.obj")}
    keys = json.loads((take / "out/keys.json").read_text())
    for reg in keys["regions"].values():
        reg["frames"] = reg["frames"][:3]
    (take / "fewer.json").write_text(json.dumps(keys))
    mine = out / "mouth" / "notes.obj"  # a file retarget did not write: never removed
    mine.write_text("v 0 0 0\n")
    assert _cli(*_pose_args(take, take / "fewer.json", out)).exit_code == 0
    second = {p.relative_to(out).as_posix() for p in out.rglob("*.obj")}
    want = {f"{n}/key_{f:05d}.obj" for n, r in keys["regions"].items() for f in r["frames"]}
    assert len(first) > len(want) and second == want | {"mouth/notes.obj"}


def test_apply_clears_only_frames_it_wrote(take):
    frames = take / "out" / "frames"
    user = frames / "frame_99999.obj"  # named like an output, but the user's
    user.write_text("v 0 0 0\n")
    w = dict(np.load(take / "out/weights.npz"))
    for k in list(w):
        if k != "meta":
            w[k] = w[k][:10] if not k.endswith("_frames") else w[k]
    np.savez(take / "short.npz", **w)
    res = _cli("apply", take / "short.npz", take / "out/targets/targets.yaml", "-o", frames)
    assert res.exit_code == 0, res.output
    left = sorted(p.name for p in frames.glob("frame_*.obj"))
    assert left == [f"frame_{t:05d}.obj" for t in range(10)] + ["frame_99999.obj"]


def _retarget() -> list[str]:
    script = Path(sys.executable).parent / "retarget"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "retarget_cli"]


def _wait_for_numpy(proc, timeout=30.0) -> bool:
    """Wait until the child has mapped numpy: it is then importing the CLI's modules (inside the entry's handler)."""
    maps = Path(f"/proc/{proc.pid}/maps")
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        try:
            if "numpy" in maps.read_text():
                return True
        except OSError:
            return False
        time.sleep(0.002)
    return False


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc to see when the CLI starts importing")
@pytest.mark.parametrize("delay", [0.0, 0.1, 0.3, 0.8])
def test_ctrl_c_at_any_moment_is_one_line_and_exit_130(take, delay):
    """SIGINT while the CLI's modules are still being imported (delay 0) or while stages run."""
    proc = subprocess.Popen([*_retarget(), "run", str(take / "config.yaml"), "--force"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert _wait_for_numpy(proc), "the command never imported numpy"
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal")
    assert "Traceback" not in err, err
    assert proc.returncode == 130, (proc.returncode, err)
    assert err.strip().splitlines()[-1] == "error: interrupted", err


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc to see when the CLI starts importing")
@pytest.mark.parametrize("sig, name", [(signal.SIGTERM, "SIGTERM"), (signal.SIGHUP, "SIGHUP")])
@pytest.mark.parametrize("delay", [0.0, 0.5])
def test_sigterm_and_sighup_unwind_like_ctrl_c(take, sig, name, delay):
    """A farm's kill (SIGTERM) or a closed terminal (SIGHUP): one line, exit 128 + signal, no temporary file left."""
    proc = subprocess.Popen([*_retarget(), "run", str(take / "config.yaml"), "--force"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert _wait_for_numpy(proc), "the command never imported numpy"
    time.sleep(delay)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal")
    assert "Traceback" not in err, err
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    assert err.strip().splitlines()[-1] == f"error: terminated ({name})", err
    assert not [p for p in take.rglob("*") if ".part" in p.name], "a temporary file was left behind"


def test_a_reader_that_stops_early_is_not_a_failure(take):
    """`retarget run ... | head -c1`: the run finishes, exits 0 and says nothing about the closed pipe."""
    proc = subprocess.Popen([*_retarget(), "run", str(take / "config.yaml"), "--force"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    assert proc.stdout.read(1)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0, err
    assert "error" not in err and "Traceback" not in err and "Exception ignored" not in err, err


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_full_stdout_is_one_warning_and_the_run_completes(take):
    with open("/dev/full", "w") as full:
        res = subprocess.run([*_retarget(), "run", str(take / "config.yaml"), "--force"], stdout=full,
                             stderr=subprocess.PIPE, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "warning: stdout: No space left on device" in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert "Exception ignored" not in res.stderr


def test_a_signal_wrapped_by_the_interpreter_is_still_a_stop():
    """Python 3.11 wraps an exception raised while a class is built (__set_name__) in a RuntimeError: a SIGTERM
    landing there must still be 'terminated', exit 143, not an internal error."""
    from retarget_cli.errors import Terminated, stop_cause, stop_message

    class Field:
        def __set_name__(self, owner, name):
            raise Terminated(signal.SIGTERM)

    try:
        type("Built", (), {"f": Field()})
    except Exception as exc:  # RuntimeError on 3.11, the Terminated itself (a BaseException) on 3.12
        wrapped = exc
    except BaseException as exc:
        wrapped = exc
    assert stop_message(stop_cause(wrapped)) == ("terminated (SIGTERM)", 143)
    assert stop_cause(RuntimeError("unrelated")) is None

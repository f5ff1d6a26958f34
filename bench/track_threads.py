"""Profile: where ``retarget track`` spends its CPU, per thread (issue 31).

Runs ``retarget -q track VIDEO -o OUT --method detect [ARGS...]`` in this process and prints:

- the process's user and system seconds (``resource.getrusage``) and its wall seconds;
- the CPU seconds of every thread, Python's (``time.thread_time`` over each thread's run, by name:
  ``MainThread``, ``retarget-track`` (frame preparation and the fusion's optical flow), ``retarget-head``,
  ``retarget-decode``) and the C library's (``/proc/self/task/*/stat`` sampled every 50 ms, by name: FFmpeg's
  decoding threads ``av:...``; a thread's last sample before it ended);
- the CPU seconds, calls and milliseconds a call of the hot functions, in the thread that ran them
  (``time.thread_time`` around each call; nested calls are counted in both). cProfile would count only the
  main thread and charge its waits for the GIL to whatever was running.

The wrappers cost a few microseconds a call. Run it from a tree with ``PYTHONPATH`` set to the code to profile.

Run: ``python bench/track_threads.py VIDEO OUT.npz [track args]``.
"""

from __future__ import annotations

import collections
import inspect
import os
import resource
import sys
import threading
import time

CPU = collections.defaultdict(lambda: [0.0, 0])  # (label, thread) -> [CPU s, calls]
THREADS = collections.defaultdict(float)
TASKS: dict[str, tuple[str, float, float]] = {}


def _thread_name() -> str:
    return threading.current_thread().name.rsplit("_", 1)[0]


def _count_threads() -> None:
    run = threading.Thread.run

    def counted(self):
        t0 = time.thread_time()
        try:
            run(self)
        finally:
            THREADS[self.name.rsplit("_", 1)[0]] += time.thread_time() - t0

    threading.Thread.run = counted


def _sample_tasks() -> None:
    tck = os.sysconf("SC_CLK_TCK")
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                st = fh.read()
        except OSError:
            continue
        f = st[st.rindex(")") + 2:].split()
        TASKS[tid] = (st[st.index("(") + 1:st.rindex(")")], int(f[11]) / tck, int(f[12]) / tck)


def wrap(owner, attr: str, label: str | None = None) -> None:
    """Count the CPU of ``owner.attr`` per calling thread."""
    if owner is None or not hasattr(owner, attr):
        return
    f = getattr(owner, attr)
    label = label or f"{getattr(owner, '__name__', str(owner)).rsplit('.', 1)[-1]}.{attr}"

    def timed(*a, **kw):
        t0 = time.thread_time()
        try:
            return f(*a, **kw)
        finally:
            e = CPU[(label, _thread_name())]
            e[0] += time.thread_time() - t0
            e[1] += 1

    if isinstance(owner, type) and isinstance(inspect.getattr_static(owner, attr), staticmethod):
        timed = staticmethod(timed)
    setattr(owner, attr, timed)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        print(__doc__.strip().splitlines()[-1], file=sys.stderr)
        return 2
    wall0, ru0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    _count_threads()
    stop = threading.Event()

    def sample():
        while not stop.wait(0.05):
            _sample_tasks()

    threading.Thread(target=sample, name="monitor", daemon=True).start()
    t0 = time.thread_time()
    from retarget_cli.entry import fix_mmap_threshold

    fix_mmap_threshold()
    from retarget_cli.cli.commands import main as cli
    from retarget_cli.io import atomic
    from retarget_cli.methods import gaps
    from retarget_cli.methods.tracking import detect, gaze, lk
    from retarget_cli.stages import track
    imports = time.thread_time() - t0

    for owner, attr in [(detect.Detector, "__init__"), (detect.Detector, "landmarks"), (detect.Detector, "detect"),
                        (detect, "_prepare_frame"), (gaps.CutDetector, "features"),
                        (detect._DetectTrack, "frame"), (detect.FlowFusion, "_flow"), (lk._Box, "flow"),
                        (detect.FlowFusion, "step"), (detect, "_frame_of"), (detect, "box_from_points"),
                        (track, "_run_tracker"), (track, "filter_segments"), (track, "_track_gaze"),
                        (track, "gaze_fn"), (gaze, "iris_centre"), (track, "_fit_heads"), (track, "fit_head"),
                        (track, "_head_pose_3d"), (track, "save_landmarks"), (track, "eye_crop"),
                        (getattr(atomic, "CropSpill", None), "add")]:
        wrap(owner, attr)
    try:
        cli.main(args=["-q", "track", argv[0], "-o", argv[1], "--method", "detect", *argv[2:]], prog_name="retarget",
                 standalone_mode=False)
    except SystemExit:
        pass
    ru = resource.getrusage(resource.RUSAGE_SELF)
    THREADS["MainThread"] = time.thread_time()
    _sample_tasks()
    stop.set()
    print(f"process: user {ru.ru_utime - ru0.ru_utime:.2f} s, system {ru.ru_stime - ru0.ru_stime:.2f} s, wall "
          f"{time.perf_counter() - wall0:.2f} s; importing the CLI (main thread) {imports:.2f} s")
    for name, s in sorted(THREADS.items(), key=lambda kv: -kv[1]):
        print(f"python thread {name:28s} {s:7.2f} s")
    by = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for comm, u, sy in TASKS.values():
        e = by[comm]
        e[0], e[1], e[2] = e[0] + u, e[1] + sy, e[2] + 1
    for comm, (u, sy, n) in sorted(by.items(), key=lambda kv: -sum(kv[1][:2])):
        print(f"OS threads {comm:20s} x{n:<3d} user {u:6.2f} s, system {sy:6.2f} s")
    for (label, who), (s, n) in sorted(CPU.items(), key=lambda kv: -kv[1][0]):
        print(f"{label:42s} {who:16s} {s:7.2f} s {n:6d} calls {1000 * s / max(n, 1):7.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

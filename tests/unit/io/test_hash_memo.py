"""File hashes memoised (io/atomic.py): once per process, and between runs in the user's memo while a file's
stat (size, mtime_ns, ctime_ns, inode) is unchanged; a file changed with its size and mtime restored is
hashed again (its ctime moved); a file changed too recently to be vouched for by its stat is not kept."""

import hashlib
import json
import os
import time

import pytest
from click.testing import CliRunner

from retarget_cli.cli.commands import main
from retarget_cli.io import atomic
from retarget_cli.io.atomic import HashMemo, hash_memo, sha256_file


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture
def fresh(monkeypatch):
    """An empty in-process memo, and files vouched for by their stat at once (no 2 s wait)."""
    monkeypatch.setattr(atomic, "_HASHES", {})
    monkeypatch.setattr(atomic, "RACY_NS", 0)
    monkeypatch.setattr(atomic, "MEMO_MIN_BYTES", 0)


def _forge(memo: HashMemo, value: str) -> None:
    """Overwrite every entry's hash: a later hit returns *value*, so the test sees the file was not read."""
    for p in memo.entries():
        doc = json.loads(p.read_text())
        doc["sha256"] = value
        p.write_text(json.dumps(doc))


def test_the_memo_is_used_by_a_new_process_while_the_file_is_unchanged(tmp_path, fresh, monkeypatch):
    f = tmp_path / "a.obj"
    f.write_bytes(b"v 1 2 3\n" * 100)
    with hash_memo(tmp_path / "hashes") as memo:
        assert sha256_file(f) == _sha(f.read_bytes())
        assert len(memo.entries()) == 1
        _forge(memo, "0" * 64)
        monkeypatch.setattr(atomic, "_HASHES", {})  # a new process
        assert sha256_file(f) == "0" * 64  # the memo was trusted: the file was not read


def test_a_file_rewritten_with_its_size_and_mtime_restored_is_hashed_again(tmp_path, fresh, monkeypatch):
    f = tmp_path / "a.obj"
    f.write_bytes(b"v 1 2 3\n")
    st = f.stat()
    with hash_memo(tmp_path / "hashes"):
        old = sha256_file(f)
        time.sleep(0.05)  # past the file system's timestamp granularity
        f.write_bytes(b"v 1 2 4\n")  # same size
        os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))  # mtime restored; the ctime cannot be
        assert f.stat().st_size == st.st_size and f.stat().st_mtime_ns == st.st_mtime_ns
        assert sha256_file(f) == _sha(b"v 1 2 4\n") != old  # the in-process memo is not fooled
        monkeypatch.setattr(atomic, "_HASHES", {})
        assert sha256_file(f) == _sha(b"v 1 2 4\n")  # nor the persistent one


def test_a_file_changed_just_now_is_not_remembered(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_HASHES", {})
    monkeypatch.setattr(atomic, "MEMO_MIN_BYTES", 0)
    f = tmp_path / "a.obj"
    f.write_bytes(b"v 1 2 3\n")
    with hash_memo(tmp_path / "hashes") as memo:
        assert sha256_file(f) == _sha(b"v 1 2 3\n")
        assert memo.entries() == [] and atomic._HASHES == {}  # within RACY_NS of its change
        f.write_bytes(b"v 1 2 4\n")  # maybe within the same timestamp tick: the stat may be the same
        assert sha256_file(f) == _sha(b"v 1 2 4\n")


def test_small_files_and_no_memo_write_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_HASHES", {})
    monkeypatch.setattr(atomic, "RACY_NS", 0)
    f = tmp_path / "a.txt"
    f.write_bytes(b"x" * 100)
    with hash_memo(tmp_path / "hashes") as memo:
        sha256_file(f)  # under MEMO_MIN_BYTES
        assert memo.entries() == []
    monkeypatch.setattr(atomic, "MEMO_MIN_BYTES", 0)
    with hash_memo(None):
        sha256_file(tmp_path / "a.txt")
    assert not (tmp_path / "hashes").exists()


def test_unreadable_or_stale_entries_are_misses(tmp_path, fresh, monkeypatch):
    f = tmp_path / "a.obj"
    f.write_bytes(b"abc")
    with hash_memo(tmp_path / "hashes") as memo:
        sha256_file(f)
        (entry,) = memo.entries()
        for junk in ("{", "[]", '{"stat": [1, 2, 3], "sha256": "' + "0" * 64 + '"}', '{"stat": 1, "sha256": 5}'):
            entry.write_text(junk)
            monkeypatch.setattr(atomic, "_HASHES", {})
            assert sha256_file(f) == _sha(b"abc")


def test_the_memo_keeps_inputs_not_outputs_and_writes_inside_a_run_guarded_elsewhere(tmp_path, fresh):
    f = tmp_path / "in" / "a.obj"
    f.parent.mkdir()
    f.write_bytes(b"abc")
    out = tmp_path / "out" / "b.obj"
    out.parent.mkdir()
    out.write_bytes(b"def")
    with atomic.guard_writes(roots=[tmp_path / "out"]), hash_memo(tmp_path / "hashes") as memo:
        assert sha256_file(f) == _sha(b"abc")
        assert len(memo.entries()) == 1
        assert sha256_file(out) == _sha(b"def")  # an output the run rewrites: this process only
        assert len(memo.entries()) == 1 and atomic._stat_key(out.stat()) in atomic._HASHES
    assert not list((tmp_path / "hashes").glob(".retarget-parts-*"))


def test_the_memo_keeps_at_most_its_limit(tmp_path, fresh, monkeypatch):
    monkeypatch.setattr(atomic, "MEMO_MAX_ENTRIES", 4)
    memo_dir = tmp_path / "hashes"
    memo_dir.mkdir()
    for i in range(6):
        (memo_dir / f"1-{i:x}.json").write_text("{}")
    (memo_dir / "notes.txt").write_text("not an entry")
    f = tmp_path / "a.obj"
    f.write_bytes(b"abc")
    with hash_memo(memo_dir) as memo:
        sha256_file(f)
        assert len(memo.entries()) == 4  # 6 -> 3, then the new one
    assert (memo_dir / "notes.txt").is_file()


def test_cache_clear_removes_the_hashes_and_no_cache_bypasses_them(small_take, fresh, user_cache, monkeypatch):
    (small_take / "keys.json").write_text("{}")
    hashes = user_cache.parent / "hashes"
    (small_take / "pose.yaml").write_text("output_dir: runout\nselect:\n  landmarks: truth_landmarks.npz\n  k: 3\n")
    res = CliRunner().invoke(main, ["run", str(small_take / "pose.yaml"), "--no-cache"])
    assert res.exit_code == 0, res.output
    assert not hashes.exists()
    monkeypatch.setattr(atomic, "_HASHES", {})  # a new process
    res = CliRunner().invoke(main, ["run", str(small_take / "pose.yaml"), "--force"])
    assert res.exit_code == 0, res.output
    n = len(HashMemo(hashes).entries())
    assert n >= 1
    res = CliRunner().invoke(main, ["cache"])
    assert f"file hashes\t{n} in {hashes}" in res.output
    (hashes / "mine.txt").write_text("keep me")
    res = CliRunner().invoke(main, ["cache", "clear"])
    assert res.exit_code == 0 and f"{hashes}: removed {n} file hash" in res.output, res.output
    assert HashMemo(hashes).entries() == [] and (hashes / "mine.txt").is_file()


def test_a_file_just_written_is_hashed_as_written(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_HASHES", {})
    f = tmp_path / "k.obj"
    atomic.write_bytes(f, b"v 1 2 3\n")
    assert atomic._HASHES == {atomic._stat_key(f.stat()): _sha(b"v 1 2 3\n")}
    assert sha256_file(f) == _sha(b"v 1 2 3\n")
    time.sleep(0.05)
    f.write_bytes(b"v 1 2 4\n")  # changed by another writer: its ctime moved, so it is hashed again
    assert sha256_file(f) == _sha(b"v 1 2 4\n")

"""The user's rig cache (io/rig/cache.py): where it is, its size limit (LRU), concurrent workers, clear."""

import os
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pytest

from retarget_cli.errors import ParameterError
from retarget_cli.io.atomic import guard_writes, savez
from retarget_cli.io.rig import cache as rigcache
from retarget_cli.io.rig import load_rig


def _entries(d):
    return sorted(p.name for p in Path(d).glob("rig-*.npz"))


def test_user_cache_dir_env_then_xdg_then_home(tmp_path):
    assert rigcache.user_cache_dir({"RETARGET_CACHE_DIR": str(tmp_path / "c"), "XDG_CACHE_HOME": "/x"}) == tmp_path / "c"
    assert rigcache.user_cache_dir({"XDG_CACHE_HOME": "/x"}) == Path("/x/retarget")
    home = Path.home()
    assert rigcache.user_cache_dir({}) == home / ".cache" / "retarget"
    assert rigcache.user_cache_dir({"XDG_CACHE_HOME": "relative"}) == home / ".cache" / "retarget"  # XDG: ignored
    assert rigcache.rig_cache_dir({"RETARGET_CACHE_DIR": "/c"}) == Path("/c/rigs")


@pytest.mark.parametrize(("text", "n"), [("", 2 << 30), ("0", 0), ("1234", 1234), ("500M", 500 << 20),
                                         ("2G", 2 << 30), ("1.5k", 1536), ("3 GiB", 3 << 30)])
def test_cache_limit(text, n):
    assert rigcache.cache_limit({"RETARGET_CACHE_SIZE": text}) == n


def test_cache_limit_refuses_junk():
    with pytest.raises(ParameterError, match="RETARGET_CACHE_SIZE: expected bytes such as 500M or 2G, got '-1'"):
        rigcache.cache_limit({"RETARGET_CACHE_SIZE": "-1"})


def _variant(take: Path, i: int) -> Path:
    """rig.yaml of the take with a changed upper bound: another cache key, same OBJs."""
    p = take / f"rig{i}.yaml"
    p.write_text((take / "rig.yaml").read_text().replace("- 1\n", f"- {i + 2}\n", 1))
    return p


def test_least_recently_used_entries_go_over_the_limit(small_take, tmp_path, monkeypatch):
    cache = tmp_path / "rigs"
    a, b, c = (_variant(small_take, i) for i in range(3))
    load_rig(a, cache_dir=cache)
    (entry_a,) = _entries(cache)
    size = (cache / entry_a).stat().st_size
    monkeypatch.setenv("RETARGET_CACHE_SIZE", str(2 * size + size // 2))  # two entries fit, not three
    load_rig(b, cache_dir=cache)
    entry_b = next(e for e in _entries(cache) if e != entry_a)
    os.utime(cache / entry_a, (1e9, 1e9))
    os.utime(cache / entry_b, (1e9 + 10, 1e9 + 10))  # b used after a ...
    ra = load_rig(a, cache_dir=cache)  # ... then a hit on a makes b the least recently used
    assert (cache / entry_a).stat().st_mtime > 1e9 + 10
    mine = cache / "notes.txt"
    mine.write_text("not the cache's")
    load_rig(c, cache_dir=cache)
    left = _entries(cache)
    assert len(left) == 2 and entry_a in left and entry_b not in left and mine.is_file()
    assert np.all(ra.upper == 2)


def test_an_entry_larger_than_the_limit_is_not_kept(small_take, tmp_path, monkeypatch):
    monkeypatch.setenv("RETARGET_CACHE_SIZE", "100")
    cold = load_rig(small_take / "rig.yaml", cache_dir=tmp_path / "rigs")
    assert _entries(tmp_path / "rigs") == []
    assert cold.neutral.tobytes() == load_rig(small_take / "rig.yaml").neutral.tobytes()


def test_the_cache_writes_inside_a_run_guarded_elsewhere(small_take, tmp_path):
    """The cache is no output of the run: its writes pass a guard of their own, only inside the cache folder."""
    with guard_writes(roots=[tmp_path / "out"], label="output_dir"):
        load_rig(small_take / "rig.yaml", cache_dir=tmp_path / "rigs")
        with pytest.raises(Exception, match="refusing to write outside output_dir"):
            savez(tmp_path / "elsewhere.npz", {"a": np.zeros(1)})
    assert len(_entries(tmp_path / "rigs")) == 1
    assert sorted(p.name for p in (tmp_path / "rigs").iterdir()) == _entries(tmp_path / "rigs")  # no journal, no part


def _load(args):
    rig_yaml, cache = args
    r = load_rig(rig_yaml, cache_dir=cache)
    return r.neutral.tobytes(), r.D.tobytes() if not r.sparse else r.D.toarray().tobytes()


def test_concurrent_workers_share_one_entry(small_take, tmp_path):
    cache = tmp_path / "rigs"
    cold = _load((small_take / "rig.yaml", None))
    with ProcessPoolExecutor(4, mp_context=get_context("fork")) as pool:
        got = list(pool.map(_load, [(small_take / "rig.yaml", cache)] * 8))
    assert all(g == cold for g in got)
    assert sorted(p.name for p in cache.iterdir()) == _entries(cache) and len(_entries(cache)) == 1


def test_an_entry_removed_between_look_up_and_read_is_a_quiet_miss(small_take, tmp_path, monkeypatch, caplog):
    cache = tmp_path / "rigs"
    cold = load_rig(small_take / "rig.yaml", cache_dir=cache)
    real_load = np.load

    def vanishing(file, *a, **k):  # another worker evicts the entry just before this one opens it
        if Path(file).parent == cache:
            os.unlink(file)
        return real_load(file, *a, **k)

    monkeypatch.setattr(rigcache.np, "load", vanishing)
    again = load_rig(small_take / "rig.yaml", cache_dir=cache)
    assert again.neutral.tobytes() == cold.neutral.tobytes()
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_clear_removes_only_entries_it_wrote(small_take, tmp_path):
    cache = tmp_path / "rigs"
    load_rig(small_take / "rig.yaml", cache_dir=cache)
    (entry,) = _entries(cache)
    other = cache / "rig-ffffffffffffffff.npz"
    savez(other, {"key": np.array("0" * 64)})  # named like an entry, holds another key
    not_npz = cache / "rig-eeeeeeeeeeeeeeee.npz"
    not_npz.write_bytes(b"user data")
    info = rigcache.cache_info(cache)
    assert info["entries"] == 1 and info["bytes"] == (cache / entry).stat().st_size
    n, size = rigcache.clear_cache(cache)
    assert n == 1 and size == info["bytes"]
    assert sorted(p.name for p in cache.iterdir()) == [not_npz.name, other.name]

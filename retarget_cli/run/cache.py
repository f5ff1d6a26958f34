"""``retarget cache``: what the user's rig cache holds, and emptying it.

The cache itself (one folder per user, shared by every run and batch worker, with a size limit) is
:mod:`retarget_cli.io.rig.cache`; this module only declares the command.
"""

from __future__ import annotations

from ..config import Command, Flag, Param
from ..io.atomic import HashMemo
from ..io.rig.cache import CACHE_DIR_ENV, CACHE_SIZE_ENV, cache_info, clear_cache, hash_memo_dir, rig_cache_dir

#: ``retarget cache``'s parameters.
CACHE_PARAMS = [
    Param("action", "setting", str, "info", "info: where the rig cache is, its entries and size; "
          "clear: remove every entry it wrote.", choices=("info", "clear")),
]


def _mb(n: int) -> str:
    return f"{n / 2**20:.1f} MB"


def _cli_cache(values, out) -> list:
    folder, memo = rig_cache_dir(), HashMemo(hash_memo_dir())
    if values["action"] == "clear":
        n, size = clear_cache(folder)
        out.echo(f"{folder}: removed {n} entr{'y' if n == 1 else 'ies'} ({_mb(size)})")
        n = memo.clear()
        out.echo(f"{memo.folder}: removed {n} file hash{'' if n == 1 else 'es'}")
        return []
    info = cache_info(folder)
    out.echo(f"folder\t{info['folder']}")
    out.echo(f"entries\t{info['entries']}")
    out.echo(f"size\t{_mb(info['bytes'])} of {_mb(info['limit'])}")
    out.echo(f"file hashes\t{len(memo.entries())} in {memo.folder}")
    return []


#: ``cache`` (the CLI builds it: :mod:`retarget_cli.cli.commands`); it writes nothing outside the cache folder.
COMMAND = Command(
    "cache",
    f"""Show the user's rig cache (info, the default) or empty it (clear).

    Commands that read a rig keep it parsed in one folder per user, shared by
    every run: ${CACHE_DIR_ENV}/rigs, else $XDG_CACHE_HOME/retarget/rigs, else
    ~/.cache/retarget/rigs. ${CACHE_SIZE_ENV} (500M, 2G; default 2G) caps its
    size: the least recently used entries go first. Beside it, hashes/ keeps
    the sha256 of the large files runs read (a rig's OBJs, a video), trusted
    while a file's size, mtime, ctime and inode are unchanged, as git and make
    do; --no-cache neither reads nor writes it. clear removes only the entries
    the cache wrote, and every file hash.
    """,
    lambda: CACHE_PARAMS,
    (Flag("action", argument=True, required=False, metavar="[info|clear]"),),
    _cli_cache,
    show=lambda result, out: None,
    guarded=False,
)

__all__ = ["CACHE_PARAMS", "COMMAND"]

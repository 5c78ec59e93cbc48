"""Writing outputs safely: never over an existing file without ``overwrite``, never over an input,
and whole or not at all (a temporary name in the same folder, renamed when complete).

Every command of the ``tofjax`` CLI checks its outputs with :func:`check_output` *before* it
does any work (a 15 s fit that cannot write its result is time lost), and writes JSON and
other small files with :func:`atomic_write_text` / :func:`atomic_path`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterable, Iterator

from .errors import UserError

__all__ = ["OutputError", "atomic_path", "atomic_write_text", "check_output", "same_file", "save_figure"]


class OutputError(UserError):
    """An output cannot (or must not) be written where asked."""


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name the same file (through links and ``..``); False if either is missing."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def check_output(
    path: str | Path,
    *,
    overwrite: bool = False,
    inputs: Iterable[str | Path | None] = (),
    folder: bool = False,
    flag: str = "--out",
) -> Path:
    """Check that ``path`` may be written; raise :class:`OutputError` in one line if not.

    - never one of ``inputs`` (whatever ``overwrite`` says), nor a folder holding one when
      ``folder`` (its files could be replaced);
    - an existing file (or, with ``folder``, a non-empty folder) only with ``overwrite``;
    - a file output is not an existing folder, and a folder output is not an existing file;
    - the parent folder can be created and written.
    """
    p = Path(path)
    if str(path) == "":
        raise OutputError(f"{flag}: an empty path")
    for inp in inputs:
        if inp is None or str(inp) == "":
            continue
        if Path(inp).exists() and same_file(p, inp):
            raise OutputError(f"{flag} {p}: is one of this command's inputs; refusing to write over it")
    if p.exists():
        if folder:
            if not p.is_dir():
                raise OutputError(f"{flag} {p}: is a file, expected a folder")
            if any(p.iterdir()) and not overwrite:
                raise OutputError(f"{flag} {p}: the folder exists and is not empty; pass --overwrite to write into it")
        else:
            if p.is_dir():
                raise OutputError(f"{flag} {p}: is a folder, expected a file name")
            if not p.is_file():  # replacing a device or a pipe would remove it
                raise OutputError(f"{flag} {p}: is not a regular file (a device, pipe or socket); refusing to write over it")
            if not overwrite:
                raise OutputError(f"{flag} {p}: exists; pass --overwrite to replace it")
    parent = p if folder else p.parent
    # The nearest existing ancestor must be a writable folder.
    anc = parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if anc.exists() and not anc.is_dir():
        raise OutputError(f"{flag} {p}: {anc} is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"{flag} {p}: {anc} is not writable")
    try:  # os.access says yes to root everywhere; a real file says whether the disk takes it
        import tempfile

        with tempfile.NamedTemporaryFile(dir=anc, prefix=".tofjax-write-test-"):
            pass
    except OSError as e:
        raise OutputError(f"{flag} {p}: {anc} is not writable ({e.strerror or e})") from None
    return p


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial-{os.getpid()}")


@contextlib.contextmanager
def atomic_path(path: str | Path, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed to ``path``, on failure removed.

    With ``overwrite=False`` the rename refuses to replace a file that appeared meanwhile
    (a hard link is made instead of a rename: it fails if the name is taken).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{path}: cannot create the folder: {e.strerror or e}") from None
    tmp = _tmp_name(path)
    try:
        yield tmp
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise OutputError(f"{path}: exists; pass --overwrite to replace it") from None
            os.unlink(tmp)
        _fsync_dir(path.parent)
    except OSError as e:
        _remove(tmp)
        raise OutputError(f"{path}: cannot write: {e.strerror or e}") from None
    except BaseException:
        _remove(tmp)
        raise


def _remove(tmp: Path) -> None:
    with contextlib.suppress(OSError):
        if tmp.is_dir():
            import shutil

            shutil.rmtree(tmp)
        else:
            tmp.unlink()


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_text(path: str | Path, text: str, *, overwrite: bool = True) -> Path:
    """Write ``text`` to ``path`` whole or not at all (temporary name, fsync, rename)."""
    path = Path(path)
    try:
        with atomic_path(path, overwrite=overwrite) as tmp:
            with open(tmp, "w") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
    except OutputError:
        raise
    except OSError as e:
        raise OutputError(f"{path}: cannot write: {e.strerror or e}") from None
    return path


def save_figure(fig, path: str | Path, *, dpi: int = 110, overwrite: bool = True) -> Path:
    """Save a matplotlib figure to ``path`` whole or not at all, then close it.

    The format comes from ``path``'s suffix (the temporary name has none of its own).
    """
    import matplotlib.pyplot as plt

    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or "png"
    try:
        with atomic_path(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, dpi=dpi, format=fmt)
    finally:
        plt.close(fig)
    return path

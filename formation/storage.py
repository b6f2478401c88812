"""Run folders on storage that Ray supports (``s3://``, ``gs://``, ``abfs://``, ``hdfs://``, ``file://``).

A run whose ``--out`` is such a URI trains in a local staging folder, and every checkpoint, the
metrics and the final results are copied up after they are written on the driver. The
checkpoint goes up as ``checkpoint.writing``, is marked complete, and only then replaces
``checkpoint``: an upload cut short leaves either the old checkpoint whole or the new one whole
and marked, and copying down takes the newest whole one. ``--resume``, ``formation evaluate``, ``export`` and
``render`` first copy a URI's run folder down. Copies go through ``pyarrow.fs``, which Ray itself
uses for its storage; credentials come from the environment as usual for each cloud.

Local outputs are never overwritten and never half-written: ``check_new_folder``, ``check_writable``
and ``check_outside`` refuse, in one line and before any work, a folder that holds something, a path
that cannot be written and an output inside its own source; ``writing_folder``, ``writing_into``
and ``write_text_whole`` write beside the target and rename.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from formation.config import ConfigError

SCHEMES = "s3://, gs://, abfs://, hdfs://, file://"
CHECKPOINT = "checkpoint"
WRITING, COMPLETE = f"{CHECKPOINT}.writing", f"{CHECKPOINT}.writing.complete"


def is_uri(path: str | Path) -> bool:
    return "://" in str(path)


def _filesystem(uri: str, what: str):
    from pyarrow import ArrowException
    from pyarrow.fs import FileSystem

    try:
        return FileSystem.from_uri(uri)
    except (ArrowException, ValueError, OSError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ConfigError(f"{what}: cannot open {uri!r} ({reason}); allowed: a local path or a URI of "
                          f"{SCHEMES}") from None


def staging_folder(uri: str) -> Path:
    """The local folder that stands in for ``uri`` on this machine (the same one every time)."""
    digest = hashlib.sha1(uri.encode()).hexdigest()[:12]
    name = uri.rstrip("/").rsplit("/", 1)[-1] or "run"
    return Path(tempfile.gettempdir()) / "formation-runs" / f"{name}-{digest}"


class RemoteRun:
    """A run folder at ``uri``, mirrored in a local staging folder."""

    def __init__(self, uri: str, what: str = "--out"):
        self.uri = uri.rstrip("/")
        self.fs, self.path = _filesystem(self.uri, what)
        self.local = staging_folder(self.uri)
        self.what = what

    def _info(self, relative: str = ""):
        from pyarrow.fs import FileType

        info = self.fs.get_file_info(f"{self.path}/{relative}".rstrip("/"))
        return info.type != FileType.NotFound, info.type == FileType.Directory

    def has_checkpoint(self) -> bool:
        return self._info(CHECKPOINT)[1]

    def check_writable(self) -> None:
        """Fail before training, in one line, when the URI cannot be written (bad bucket, no credentials)."""
        try:
            self.fs.create_dir(self.path, recursive=True)
        except OSError as err:
            raise ConfigError(f"{self.what}: cannot write to {self.uri!r} ({str(err).splitlines()[0]})") from None

    def pull(self) -> Path:
        """Copy the run folder down into the (emptied) staging folder; return it."""
        from pyarrow.fs import LocalFileSystem

        exists, is_dir = self._info()
        if not is_dir:
            what = "is a file" if exists else "does not exist"
            raise ConfigError(f"{self.what}: {self.uri!r} {what}; give the URI of a run folder")
        shutil.rmtree(self.local, ignore_errors=True)
        self.local.mkdir(parents=True)
        _copy(self.path, self.fs, str(self.local), LocalFileSystem())
        writing, marker = self.local / WRITING, self.local / COMPLETE
        if writing.is_dir() and marker.is_file():  # an upload stopped after the new checkpoint was whole
            shutil.rmtree(self.local / CHECKPOINT, ignore_errors=True)
            writing.rename(self.local / CHECKPOINT)
        shutil.rmtree(writing, ignore_errors=True)
        marker.unlink(missing_ok=True)
        return self.local

    def push(self) -> None:
        """Copy the staging folder up: every file, then the checkpoint through ``checkpoint.writing``."""
        from pyarrow.fs import LocalFileSystem

        local_fs = LocalFileSystem()
        self.fs.create_dir(self.path, recursive=True)
        for item in sorted(self.local.iterdir()):
            if item.name.startswith(CHECKPOINT):
                continue
            _copy(str(item), local_fs, f"{self.path}/{item.name}", self.fs)
        checkpoint = self.local / CHECKPOINT
        if not checkpoint.is_dir():
            return
        writing, final, marker = (f"{self.path}/{name}" for name in (WRITING, CHECKPOINT, COMPLETE))
        for old in (marker, writing):
            self._delete(old)
        _copy(str(checkpoint), local_fs, writing, self.fs)
        with self.fs.open_output_stream(marker) as out:
            out.write(b"checkpoint.writing is whole\n")
        self._delete(final)
        _copy(writing, self.fs, final, self.fs)
        self._delete(marker)
        self._delete(writing)

    def _delete(self, path: str) -> None:
        from pyarrow.fs import FileType

        kind = self.fs.get_file_info(path).type
        if kind == FileType.Directory:
            self.fs.delete_dir(path)
        elif kind != FileType.NotFound:
            self.fs.delete_file(path)


def _copy(source: str, source_fs, destination: str, destination_fs) -> None:
    """A file or a whole folder. pyarrow makes the folders below a copied folder, not the folder itself."""
    from pyarrow.fs import FileType, copy_files

    if source_fs.get_file_info(source).type == FileType.Directory:
        destination_fs.create_dir(destination, recursive=True)
    copy_files(source, destination, source_filesystem=source_fs, destination_filesystem=destination_fs)


def local_run_folder(path: str | Path, what: str = "checkpoint") -> Path:
    """``path`` itself, or for a storage URI a local copy of the folder it names."""
    if not is_uri(path):
        return Path(path)
    return RemoteRun(str(path), what=what).pull()


# ---------------------------------------------------------------------- local outputs: nothing overwritten
def _nearest_existing(path: Path) -> Path:
    for folder in (path, *path.parents):
        if folder.exists():
            return folder
    return Path(".")


def check_writable(path: str | Path, what: str) -> Path:
    """Fail in one line, before any work, when ``path`` (a local file or folder to be made) cannot be written."""
    if is_uri(path):
        raise ConfigError(f"{what}: {str(path)!r} is a storage URI; allowed: a local path (copy it up afterwards)")
    path = Path(path)
    folder = _nearest_existing(path.parent)
    if not folder.is_dir():
        raise ConfigError(f"{what}: cannot make {str(path)!r}: {str(folder)!r} is a file, not a folder")
    for place in (folder, path) if path.is_dir() else (folder,):  # beside it, and into a folder that is there
        try:  # os.access says yes to root on read-only or virtual file systems (/proc): try it
            os.rmdir(tempfile.mkdtemp(prefix=".formation-probe-", dir=place))
        except OSError as err:
            raise ConfigError(f"{what}: cannot write in {str(place)!r} ({err.strerror or err})") from None
    return path


def check_new_folder(path: str | Path, what: str, source: str | Path | None = None) -> Path:
    """``path`` must be a new (or empty) folder that can be made, outside ``source`` if given: what is
    there is never overwritten."""
    if source is not None and not is_uri(source):
        check_outside(path, source, what)
    path = check_writable(path, what)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        kind = "a folder that is not empty" if path.is_dir() else "a file"
        raise ConfigError(f"{what}: {str(path)!r} is {kind}; allowed: a new or empty folder (nothing is "
                          f"overwritten)")
    return path


def check_outside(path: str | Path, source: str | Path, what: str, given: str | None = None) -> None:
    """An output never goes onto, or into, the folder it is made from."""
    inside, origin = Path(path).resolve(), Path(source).resolve()
    if inside == origin:
        raise ConfigError(f"{what}: {str(path)!r} is the folder it is made from; allowed: a folder outside it")
    if origin in inside.parents:
        raise ConfigError(f"{what}: {str(path)!r} is inside {given or str(source)!r}, the folder it is made from; "
                          f"allowed: a folder outside it")


def _temporary_beside(path: Path, inside: bool = False) -> Path:
    folder = path if inside else path.parent
    temporary = folder / f".{path.name or 'out'}.writing-{os.getpid()}-{secrets.token_hex(3)}"
    temporary.mkdir()  # mkdir, unlike mkdtemp, keeps the usual permissions
    return temporary


@contextmanager
def writing_folder(path: str | Path) -> Iterator[Path]:
    """A fresh folder beside ``path`` to write into, renamed to ``path`` when the block ends well and
    removed (with the parent folders it made) when it does not: ``path`` appears whole or not at all."""
    path = Path(path).absolute()
    made = [folder for folder in path.parents if not folder.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = _temporary_beside(path)
    try:
        yield temporary
        os.rename(temporary, path)  # onto an empty folder, or nothing; never onto files
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        for folder in made:  # the deepest first
            with suppress(OSError):
                folder.rmdir()
        raise


@contextmanager
def writing_into(path: str | Path) -> Iterator[Path]:
    """A fresh folder to write files into; when the block ends well each file moves into ``path`` whole
    (replacing one of the same name: a command's own earlier output), and ``path`` is made if new."""
    path = Path(path).absolute()
    if not path.exists():
        with writing_folder(path) as temporary:
            yield temporary
        return
    temporary = _temporary_beside(path, inside=True)
    try:
        yield temporary
        for item in sorted(temporary.iterdir()):
            os.replace(item, path / item.name)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)


def write_text_whole(path: str | Path, text: str) -> Path:
    """Write ``text`` beside ``path`` and rename it there: a reader sees the old file or the new one, never half."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.writing-{os.getpid()}-{secrets.token_hex(3)}")
    try:
        temporary.write_text(text)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path

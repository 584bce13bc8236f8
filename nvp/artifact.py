"""One on-disk format for every saved object: a versioned JSON manifest beside an ``.npz`` of arrays.

``save_artifact(path, kind, version, arrays, manifest)`` writes ``<stem>.npz`` and ``<stem>.json`` with one
commit point: the arrays go to a new hidden file first, then the manifest naming that file replaces the old
manifest (the commit), then the arrays take their plain name and the manifest follows — at every moment the
manifest names arrays of its own size and sha256, so a reader (or a run killed anywhere) sees either the
old pair or the new one. The manifest records the format name, its version, the arrays file, its size and
its sha256.
``load_artifact(path, kind, versions)`` checks all of that and raises one :class:`FormatError` that says what
was expected and what was found (a truncated, emptied or swapped arrays file included). Nothing is pickled.

Layout of a manifest::

    {"format": "nvp.<kind>", "version": 3, "arrays": "<stem>.npz", "bytes": 1234, "sha256": "…", …}

Writing is crash-safe (temporary name, ``fsync`` of the file, ``os.replace``, ``fsync`` of the folder: a
power cut leaves the old file or the new one, not an empty one) and a full disk is reported as
"disk full while writing PATH" (:class:`DiskFullError`), never as a half-written file. Checkpoints of the
trainers are written with :func:`atomic_path` too, and read with :func:`load_checkpoint` (a damaged one is
one error that names it).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import secrets
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nvp.errors import FormatError, NvpError

LOAD_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)
"""What reading a damaged ``.npz`` / ``.json`` can raise."""


class DiskFullError(NvpError):
    """The disk filled up while nvp wrote a file (nothing half-written was left behind)."""


@dataclass(frozen=True)
class Artifact:
    """A loaded artifact.

    Attributes:
        manifest: the parsed JSON manifest (format, version, arrays, bytes, sha256 and the object's fields).
        arrays: name → array, fully read into memory.
        path: the manifest's path.
    """

    manifest: dict
    arrays: dict[str, np.ndarray] = field(repr=False)
    path: Path


def manifest_path(path: str | os.PathLike[str]) -> Path:
    """The ``.json`` manifest of an artifact given by its manifest, arrays file or stem."""
    p = Path(path)
    return p if p.suffix == ".json" else p.with_name(p.name.removesuffix(".npz") + ".json")


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    """sha256 hex digest of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def is_disk_full(e: BaseException) -> bool:
    """Whether an exception says the disk is full (ENOSPC / EDQUOT, or zipfile's short-write message)."""
    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    return "requested and" in str(e) and "written" in str(e)


def fsync_path(path: Path) -> None:
    """Flush a file's (or a folder's: its entries) data to the disk; folders of file systems that cannot
    (some network mounts) are left as they are."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        if path.is_dir():
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not path.is_dir():
            raise
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a hidden temporary path beside ``path``; on success it is flushed to the disk and renamed to
    ``path`` (the commit point), and the folder is flushed; on any error it is removed (a full disk
    becomes :class:`DiskFullError`). ``path``'s folder is created if missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if is_disk_full(e):
            raise DiskFullError(f"disk full while writing {path}") from e
        raise


def check_output_file(path: str | os.PathLike[str], inputs: tuple = ()) -> Path:
    """Check, before any work, that ``path`` can be written as an output file: it is none of the
    ``inputs``, not a folder, and a file can be created in its folder (or the nearest existing parent)."""
    path = Path(path)
    for i in inputs:
        if Path(i).exists() and path.exists() and path.resolve() == Path(i).resolve():
            raise NvpError(f"the output {path} is also an input; choose another output name")
    if path.is_dir():
        raise NvpError(f"the output {path} is a folder; give a file name (e.g. {path / 'out.mp4'})")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise NvpError(f"cannot write {path}: the folder {parent} is not writable")
    try:  # permissions can say yes where no file can be made (/proc, a full disk, some network mounts)
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise NvpError(f"cannot write {path}: no file can be created in {parent} ({e.strerror})") from None
    return path


def write_json(path: str | os.PathLike[str], data: dict) -> Path:
    """Write ``data`` as indented JSON atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path


def save_artifact(
    path: str | os.PathLike[str],
    kind: str,
    version: int,
    arrays: dict[str, np.ndarray],
    manifest: dict | None = None,
    compress: bool = False,
) -> Path:
    """Write ``<stem>.npz`` (``arrays``) and ``<stem>.json`` (``manifest`` plus the format fields).

    Args:
        path: the manifest path, the arrays path or their common stem.
        kind: format name without the ``nvp.`` prefix (e.g. ``"tracked_sequence"``).
        version: format version of ``kind``.
        arrays: name → array (numeric or bool; object arrays are refused).
        manifest: JSON-serialisable fields of the object.
        compress: zip-deflate the arrays (smaller, slower).

    Returns:
        The manifest path.
    """
    js = manifest_path(path)
    npz = js.with_suffix(".npz")
    for name, a in arrays.items():
        if np.asarray(a).dtype == object:
            raise ValueError(f"array {name!r} has dtype object; artifacts hold numeric arrays only")
    staged = js.with_name(f".{npz.stem}.{os.getpid()}-{secrets.token_hex(4)}.npz")
    with atomic_path(staged) as tmp:
        with open(tmp, "wb") as f:
            (np.savez_compressed if compress else np.savez)(f, **arrays)
    try:
        m = {
            "format": f"nvp.{kind}",
            "version": int(version),
            "arrays": staged.name,
            "bytes": staged.stat().st_size,
            "sha256": file_sha256(staged),
            **(manifest or {}),
        }
        write_json(js, m)  # the commit point: from here on readers get the new arrays
    except BaseException:
        if _named_arrays(js) != staged.name:  # (an error after the rename leaves the new pair whole)
            staged.unlink(missing_ok=True)
        raise
    # the plain name: a link to the same data replaces the old arrays, then the manifest names it
    with atomic_path(npz) as tmp:
        try:
            os.link(staged, tmp)
        except OSError:  # a file system without hard links
            shutil.copyfile(staged, tmp)
    write_json(js, {**m, "arrays": npz.name})
    for old in js.parent.glob(f".{npz.stem}.*.npz"):  # this save's, and those of saves killed before
        if old.name != npz.name and _staged_by_gone_or_me(old):
            old.unlink(missing_ok=True)
    return js


def _named_arrays(js: Path) -> str | None:
    """The arrays file the manifest ``js`` names (None when it cannot be read)."""
    try:
        return json.loads(js.read_text()).get("arrays")
    except (OSError, ValueError, AttributeError):
        return None


def _staged_by_gone_or_me(path: Path) -> bool:
    """Whether staged arrays ``.<stem>.<pid>-<hex>.npz`` were written by this process or by one that is
    gone (another process saving the same artifact right now keeps its own)."""
    try:
        pid = int(path.name.rsplit(".", 2)[-2].split("-", 1)[0])
    except (ValueError, IndexError):
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    return False


def read_manifest(path: str | os.PathLike[str], kind: str, versions: tuple[int, ...] | int) -> dict:
    """The manifest of an artifact, checked for its format name and a supported version."""
    js = manifest_path(path)
    versions = (versions,) if isinstance(versions, int) else tuple(versions)
    try:
        m = json.loads(js.read_text())
    except FileNotFoundError as e:
        raise FormatError(f"{js} is missing") from e
    except (OSError, ValueError) as e:
        raise FormatError(f"cannot read {js}: {e}") from e
    if not isinstance(m, dict) or m.get("format") != f"nvp.{kind}" or m.get("version") not in versions:
        found = (m.get("format"), m.get("version")) if isinstance(m, dict) else (type(m).__name__, None)
        raise FormatError(
            f"{js}: expected nvp.{kind} version {' or '.join(map(str, versions))}, "
            f"found {found[0]} version {found[1]}"
        )
    return m


def check_arrays_file(js: Path, m: dict) -> Path:
    """The arrays file named by manifest ``m`` of ``js``, checked against the recorded size and sha256
    (manifests written before these were recorded are checked when their arrays are read)."""
    npz = js.parent / m.get("arrays", js.with_suffix(".npz").name)
    if not npz.is_file():
        raise FormatError(f"{npz} is missing (named by {js.name})")
    size = npz.stat().st_size
    if "bytes" in m and size != m["bytes"]:
        raise FormatError(f"{npz} is damaged: {size} bytes, its manifest says {m['bytes']} (truncated?)")
    if "sha256" in m and file_sha256(npz) != m["sha256"]:
        raise FormatError(f"{npz} is damaged: its sha256 does not match its manifest {js.name}")
    return npz


def load_artifact(path: str | os.PathLike[str], kind: str, versions: tuple[int, ...] | int) -> Artifact:
    """Read and check an artifact written by :func:`save_artifact` (see :func:`read_manifest` and
    :func:`check_arrays_file`); every array is read into memory."""
    js = manifest_path(path)
    m = read_manifest(js, kind, versions)
    npz = check_arrays_file(js, m)
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except LOAD_ERRORS as e:
        raise FormatError(f"cannot read {npz}: {e or type(e).__name__}") from e
    return Artifact(m, arrays, js)


def load_checkpoint(path: str | os.PathLike[str], device: str = "cpu") -> dict:
    """A trainer's checkpoint (``torch.load`` with ``weights_only``); one :class:`FormatError` naming it when
    it cannot be read (cut short, emptied, junk: torch raises zip, pickle or EOF errors)."""
    import torch

    try:
        state = torch.load(path, weights_only=True, map_location=device)
    except Exception as e:  # noqa: BLE001 - whatever the damage, the answer is the same
        why = str(e).splitlines()[0][:120] if str(e) else type(e).__name__
        raise FormatError(
            f"the training checkpoint {path} is damaged and cannot be read ({why}); delete it to start "
            "training again"
        ) from e
    if not isinstance(state, dict):
        raise FormatError(
            f"the training checkpoint {path} holds a {type(state).__name__}, not a checkpoint; delete it to "
            "start training again"
        )
    return state

"""Fetching a catalogue dataset: download (resumable), check, unpack safely, arrange, rename into place.

``fetch(dataset, to)`` makes ``to/<dataset.folder>``, a folder the explorer opens in
``dataset.layout``, from the dataset's ``catalogue.Download`` files:

1. **Skip or refuse.** A target folder that already exists is skipped: nothing is
   downloaded or changed (``FetchResult.skipped``); delete or rename it to fetch again. A
   dataset whose ``access`` is not ``download`` is refused by name with what to do.
2. **Download** each file with ``urllib`` into ``to/.downloads/<file_name>.part``. A
   ``.part`` left by an interrupted run is resumed with ``Range: bytes=N-``; a server that
   answers ``200`` instead of ``206`` sends the whole file, which replaces the ``.part`` from
   its start. A dropped connection, a timeout (``TIMEOUT``, 30 s without data) or a body
   shorter than its ``Content-Length`` stops with one ``VPRInputError`` that keeps the
   ``.part`` for the next run. The complete file is renamed to ``<file_name>``.
3. **Check** its sha256 against the catalogue's (or the caller's ``sha256``, for the one
   file without a published digest). A mismatch deletes the file (resuming it would not
   help) and stops. Files without a digest are not verified: their sha256 is returned, to
   be pinned.
4. **Unpack** into a hidden temporary folder beside the target (``settings.temporary_name``)
   after checking every member: absolute paths, ``..`` components, links whose target lies
   outside the folder, devices, FIFOs (and any link inside a zip) are refused before anything
   is written; the declared size of what is kept must fit the free space; a zip member that
   yields more than its declared size is refused. Tar members are extracted through
   ``tarfile``'s ``data`` filter as well. Only the archive's ``member`` folder is kept where
   one is named; an archive holding one folder and nothing else is that folder. A damaged
   archive (truncated, bad CRC) deletes the downloaded file and stops.
5. **Arrange and check**: ``FILE`` downloads are placed at ``place_as`` (VPR-Bench's ground
   truth, over any copy in the archive); the folder must open in the dataset's layout
   (``layouts.detect_layout`` then its loader), else nothing is kept.
6. **Rename into place** (one ``os.rename`` on the same file system), then delete the
   downloaded files. On any failure, Ctrl-C included, the temporary folder is removed: no
   half-written dataset folder is ever left; only ``.part`` files stay, for resuming.

The data folder defaults to ``$VPR_EXPLORER_DATA``, else ``~/vpr-data`` (``DEFAULT_DATA``).
``mirror`` (``--from URL``, ``$VPR_EXPLORER_MIRROR``) replaces every download's URL with
``MIRROR/<file_name>``: a local copy, a mirror, the tests' server. Progress goes through an
optional ``progress(done, total, file name)`` callback, in bytes of the file being downloaded
(``total`` 0 when the server does not say).
"""

from __future__ import annotations

import hashlib
import http.client
import os
import re
import shutil
import stat
import tarfile
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from urllib.error import HTTPError, URLError
from urllib.parse import quote
from urllib.request import Request, urlopen

import vpr_explorer
from vpr_explorer.data.catalogue import Access, Download, PublicDataset, Unpack
from vpr_explorer.data.layouts import RETRIEVAL_LAYOUTS, Layout, detect_layout, load_retrieval
from vpr_explorer.data.traversals import load_traversal_folders
from vpr_explorer.errors import VPRInputError
from vpr_explorer.settings import DATA_ENV, temporary_name

MIRROR_ENV = "VPR_EXPLORER_MIRROR"
"""A base URL that serves every download as ``BASE/<file_name>`` (``--from URL``)."""
DEFAULT_DATA = Path("~/vpr-data")
"""The data folder when ``VPR_EXPLORER_DATA`` is unset."""
DOWNLOADS = ".downloads"
"""The hidden folder of the data folder that holds downloads in progress (``.part``)."""
TIMEOUT = 30.0
"""Seconds to wait for a connection or for the next bytes before giving up (resumable)."""
CHUNK = 1 << 20
"""Bytes read and written at a time."""
USER_AGENT = f"vpr-explorer/{vpr_explorer.__version__} (urllib)"

#: called with (bytes done, bytes in all, file name); ``total`` is 0 when the server did not say
Progress = Callable[[int, int, str], None]
_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")
_ACCESS_REASON = {
    Access.RSYNC: "is served over rsync only, which fetch does not run",
    Access.SCRIPT: "needs the downloader's own formatting script",
    Access.REQUEST: "is not public: its images are given on request",
}


@dataclass(frozen=True)
class Digest:
    """The sha256 of one downloaded file and whether it was checked.

    Attributes:
        file_name, url: the file and where it came from.
        sha256: its hex digest.
        checked: it equalled the catalogue's digest, or the caller's.
    """

    file_name: str
    url: str
    sha256: str
    checked: bool


@dataclass(frozen=True)
class FetchResult:
    """What ``fetch`` did.

    Attributes:
        path: the dataset folder (``--dataset`` of the other commands).
        skipped: it existed already, and nothing was downloaded or changed.
        digests: the sha256 of every downloaded file.
    """

    path: Path
    skipped: bool
    digests: tuple[Digest, ...] = ()


def data_folder(environ: Mapping[str, str] = os.environ) -> Path:
    """Where datasets are fetched to by default: ``$VPR_EXPLORER_DATA``, else ``~/vpr-data``."""
    value = environ.get(DATA_ENV, "").strip()
    return Path(value or DEFAULT_DATA).expanduser()


def url_of(download: Download, mirror: str | None = None) -> str:
    """Where ``download`` is fetched from: its URL, or ``MIRROR/<file_name>``."""
    if mirror:
        return f"{mirror.rstrip('/')}/{quote(download.file_name)}"
    return download.url


def sha256_of(path: Path) -> str:
    """The hex sha256 of a file, read in chunks."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


# --------------------------------------------------------------------------- download


def _dropped(url: str, part: Path, done: int, total: int | None, why: object) -> VPRInputError:
    size = f"{done:,} of {total:,} bytes" if total else f"{done:,} bytes"
    return VPRInputError(f"{url}: the download stopped after {size} ({why}); the part is kept in {part}: "
                         "run the same command again to resume it")


def download(url: str, part: Path, *, progress: Progress | None = None, timeout: float = TIMEOUT,
             _restarted: bool = False) -> None:
    """Download ``url`` into ``part``, resuming from the bytes ``part`` already holds.

    Sends ``Range: bytes=N-`` when ``part`` holds N > 0 bytes and appends a ``206`` answer
    whose ``Content-Range`` starts at N; any other success rewrites ``part`` from the start.
    ``416`` (nothing past N) means ``part`` is complete when the server's size is N, else
    ``part`` is discarded and the download restarts once.

    Raises:
        VPRInputError: the host cannot be reached, an HTTP error, the connection dropped
            (``part`` kept, to resume), ``part`` cannot be written.
    """
    have = part.stat().st_size if part.is_file() else 0
    headers = {"User-Agent": USER_AGENT, "Accept-Encoding": "identity"}
    if have:
        headers["Range"] = f"bytes={have}-"
    try:
        response = urlopen(Request(url, headers=headers), timeout=timeout)
    except HTTPError as exc:
        if exc.code == 416 and have and not _restarted:
            match = re.fullmatch(r"bytes\s+\*/(\d+)", exc.headers.get("Content-Range", "").strip())
            if match and int(match[1]) == have:
                return
            part.unlink()
            return download(url, part, progress=progress, timeout=timeout, _restarted=True)
        raise VPRInputError(f"{url}: HTTP {exc.code} {exc.reason}; check the address (or the mirror given with "
                            f"--from / {MIRROR_ENV}) and try again") from None
    except (URLError, OSError, http.client.HTTPException) as exc:
        reason = getattr(exc, "reason", exc)
        raise VPRInputError(f"{url}: cannot connect ({reason}); check the network, or name a mirror with --from URL "
                            f"({MIRROR_ENV})") from None
    with response:
        length = response.headers.get("Content-Length")
        match = _CONTENT_RANGE.fullmatch(response.headers.get("Content-Range", "").strip())
        if response.status == 206 and match and int(match[1]) == have:
            mode, done = "ab", have
            total = int(match[3]) if match[3] != "*" else (have + int(length) if length else None)
        elif response.status == 206:  # a range we did not ask for: start again from nothing
            response.close()
            part.unlink(missing_ok=True)
            if _restarted:
                raise VPRInputError(f"{url}: the server answered a range it was not asked for; try again later")
            return download(url, part, progress=progress, timeout=timeout, _restarted=True)
        else:  # 200: the server ignored Range (or none was sent) and sends the whole file
            mode, done = "wb", 0
            total = int(length) if length else None
        try:
            fh = open(part, mode)
        except OSError as exc:
            raise VPRInputError(f"{part}: cannot write it ({exc.strerror}); pick a writable --to folder") from None
        with fh:
            while True:
                try:
                    chunk = response.read(CHUNK)
                except (OSError, http.client.HTTPException) as exc:
                    raise _dropped(url, part, done, total, str(exc) or type(exc).__name__) from None
                if not chunk:
                    break
                try:
                    fh.write(chunk)
                except OSError as exc:
                    raise VPRInputError(f"{part}: cannot write it ({exc.strerror}); free some space or pick another "
                                        "--to folder, then run the same command again to resume") from None
                done += len(chunk)
                if progress is not None:
                    progress(done, total or 0, part.name.removesuffix(".part"))
    if total is not None and done < total:
        raise _dropped(url, part, done, total, "the connection closed early")


# --------------------------------------------------------------------------- unpack


def _unsafe_name(name: str) -> str | None:
    """Why an archive member's name may not be extracted, or ``None``."""
    if not name or "\x00" in name:
        return "an empty name or a NUL character"
    if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name):
        return "an absolute path"
    if ".." in re.split(r"[\\/]+", name):
        return "a '..' component"
    return None


def _kept(name: str, member: str) -> str | None:
    """The path of ``name`` below ``member`` (``""``: every name), or ``None`` when it lies elsewhere."""
    name = name.rstrip("/")
    if not member:
        return name
    if name == member:
        return ""
    return name[len(member) + 1:] if name.startswith(member + "/") else None


def _refuse(archive: Path, name: str, why: str) -> VPRInputError:
    return _BadArchive(f"{archive}: member {name!r} is refused ({why}); nothing was extracted. The archive is not "
                         "what the catalogue expects: report it, or fetch from another mirror")


def _check_room(archive: Path, needed: int, folder: Path) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free:
        raise VPRInputError(f"{archive}: unpacks to {needed:,} bytes but {folder} has {free:,} free; free some space "
                            "or pick another --to folder")


def _unpack_tar(archive: Path, member: str, into: Path) -> None:
    with tarfile.open(archive, "r:gz") as tar:
        members = tar.getmembers()
        chosen, needed = [], 0
        for info in members:
            why = _unsafe_name(info.name)
            if why is None and not (info.isreg() or info.isdir() or info.issym() or info.islnk()):
                why = "a device, FIFO or other special file"
            if why is None and info.issym():
                target = PurePosixPath(info.name).parent / info.linkname
                if info.linkname.startswith("/") or _unsafe_name(os.path.normpath(str(target))) is not None:
                    why = f"a symbolic link to {info.linkname!r}, outside the folder"
            if why is None and info.islnk() and _unsafe_name(info.linkname) is not None:
                why = f"a hard link to {info.linkname!r}, outside the folder"
            if why is not None:
                raise _refuse(archive, info.name, why)
            rel = _kept(info.name, member)
            if not rel:
                continue
            if info.islnk():
                linked = _kept(info.linkname, member)
                if not linked:
                    raise _refuse(archive, info.name, f"a hard link to {info.linkname!r}, outside the kept folder")
                info = info.replace(linkname=linked, deep=False)
            chosen.append(info.replace(name=rel, deep=False))
            needed += info.size if info.isreg() else 0
        if member and not chosen:
            raise _BadArchive(f"{archive}: holds no {member}/; the archive is not what the catalogue expects")
        _check_room(archive, needed, into)
        tar.extractall(into, members=chosen, filter="data")


def _unpack_zip(archive: Path, member: str, into: Path) -> None:
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        chosen, needed = [], 0
        for info in infos:
            why = _unsafe_name(info.filename)
            mode = info.external_attr >> 16
            if why is None and stat.S_ISLNK(mode):
                why = "a symbolic link (links in a zip are not extracted)"
            elif why is None and mode and stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                why = "a device, FIFO or other special file"
            if why is not None:
                raise _refuse(archive, info.filename, why)
            rel = _kept(info.filename, member)
            if rel:
                chosen.append((info, rel))
                needed += info.file_size
        if member and not chosen:
            raise _BadArchive(f"{archive}: holds no {member}/; the archive is not what the catalogue expects")
        _check_room(archive, needed, into)
        root = into.resolve()
        for info, rel in chosen:
            dest = into / rel
            if not dest.resolve().is_relative_to(root):  # no name above passes; a second guard
                raise _refuse(archive, info.filename, "it would be written outside the folder")
            if info.is_dir():
                dest.mkdir(parents=True, exist_ok=True)
                continue
            dest.parent.mkdir(parents=True, exist_ok=True)
            written = 0
            with zf.open(info) as src, open(dest, "wb") as out:
                while chunk := src.read(CHUNK):
                    written += len(chunk)
                    if written > info.file_size:
                        raise _refuse(archive, info.filename, f"it holds more than its declared {info.file_size:,} "
                                                              "bytes")
                    out.write(chunk)


class _BadArchive(VPRInputError):
    """A downloaded archive that cannot be used (damaged, or refused): deleted, so that no later run reuses it."""


def unpack(archive: Path, kind: Unpack, member: str, into: Path) -> None:
    """Unpack ``archive`` (zip or tar.gz) into the folder ``into``, keeping only ``member``'s folder when named.

    Raises:
        VPRInputError: an unsafe member (nothing extracted), too little space, a damaged
            archive (named, with the fix).
    """
    try:
        if kind is Unpack.ZIP:
            _unpack_zip(archive, member.rstrip("/"), into)
        elif kind is Unpack.TAR_GZ:
            _unpack_tar(archive, member.rstrip("/"), into)
        else:
            raise VPRInputError(f"{archive}: {kind.value} is not an archive")
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, zipfile.LargeZipFile) as exc:
        if isinstance(exc, tarfile.FilterError):  # the data filter's own refusal, after the checks above
            raise _refuse(archive, exc.tarinfo.name, str(exc)) from None
        raise _BadArchive(f"{archive}: the archive is damaged or truncated ({str(exc) or type(exc).__name__}); run "
                          "the same command again to fetch it afresh") from None


# --------------------------------------------------------------------------- fetch


def _refuse_access(dataset: PublicDataset) -> VPRInputError:
    return VPRInputError(f"dataset {dataset.name!r} ({dataset.title}) {_ACCESS_REASON[dataset.access]}: "
                         f"{dataset.how}")


def _expected(dataset: PublicDataset, sha256: str | None) -> list[str | None]:
    """Each download's expected digest: the catalogue's, and ``sha256`` for the one without."""
    expected = [d.sha256 for d in dataset.downloads]
    if sha256 is None:
        return expected
    if not re.fullmatch(r"[0-9a-fA-F]{64}", sha256):
        raise VPRInputError(f"--sha256 {sha256!r}: give 64 hexadecimal digits")
    open_ = [i for i, e in enumerate(expected) if e is None]
    if len(open_) != 1:
        raise VPRInputError(f"--sha256: {dataset.name} has {len(open_)} files without a published digest; it "
                            "applies only where exactly one file lacks one")
    expected[open_[0]] = sha256.lower()
    return expected


def _single_folder(folder: Path) -> Path:
    """``folder``, or the one folder it holds when it holds nothing else (hidden entries aside)."""
    shown = [p for p in folder.iterdir() if not p.name.startswith(".")]
    if len(shown) == 1 and shown[0].is_dir() and not shown[0].is_symlink():
        return shown[0]
    return folder


def _check_layout(root: Path, dataset: PublicDataset) -> None:
    """The unpacked folder opens in the dataset's layout (listing only: no image is decoded)."""
    found = detect_layout(root)
    if found is not dataset.layout:
        names = ", ".join(sorted(p.name for p in root.iterdir())[:8])
        raise VPRInputError(f"{dataset.name}: the archive unpacked into a {found.value} folder ({names}), not the "
                            f"{dataset.layout.value} layout the catalogue expects; nothing was kept")
    if dataset.layout in RETRIEVAL_LAYOUTS:
        load_retrieval(root, dataset.layout)
    elif dataset.layout is Layout.TRAVERSALS:
        load_traversal_folders(root)


def fetch(dataset: PublicDataset, to: Path | None = None, *, mirror: str | None = None, sha256: str | None = None,
          progress: Progress | None = None, timeout: float = TIMEOUT) -> FetchResult:
    """Fetch ``dataset`` into ``to/<dataset.folder>`` (module doc: skip, download, check, unpack, arrange, rename).

    Args:
        to: the data folder (default ``data_folder()``); created when missing.
        mirror: a base URL serving every file as ``MIRROR/<file_name>`` (default none: the catalogue's URLs).
        sha256: the expected digest of the one file the catalogue has none for.
        progress: ``progress(done, total, file name)`` in bytes while downloading.
        timeout: seconds without an answer or data before a download stops (resumable).

    Raises:
        VPRInputError: one line naming the URL or file and what to do; no dataset folder is
            left half-written (a ``.part`` download is kept, to resume).
    """
    to = (data_folder() if to is None else Path(to)).expanduser()
    target = to / dataset.folder
    if target.exists() or target.is_symlink():
        return FetchResult(path=target, skipped=True)
    if dataset.access is not Access.DOWNLOAD:
        raise _refuse_access(dataset)
    expected = _expected(dataset, sha256)
    downloads = to / DOWNLOADS
    try:
        downloads.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VPRInputError(f"--to {to}: cannot create {downloads} ({exc.strerror}); pick a writable folder") from None
    files, digests = [], []
    for item, want in zip(dataset.downloads, expected):
        url = url_of(item, mirror)
        path = downloads / item.file_name
        if not path.is_file():
            part = downloads / f"{item.file_name}.part"
            download(url, part, progress=progress, timeout=timeout)
            os.replace(part, path)
        got = sha256_of(path)
        if want is not None and got != want.lower():
            path.unlink()
            raise VPRInputError(f"{url}: sha256 {got} differs from the expected {want}; the file was deleted. Run the "
                                "command again to download it afresh; if it differs again, the file changed at its "
                                "source or on the mirror: do not use it unchecked")
        files.append(path)
        digests.append(Digest(item.file_name, url, got, want is not None))
    staging = to / temporary_name(dataset.folder)
    staging.mkdir()
    try:
        work = staging / "unpacked"
        work.mkdir()
        for item, path in zip(dataset.downloads, files):
            if item.unpack is not Unpack.FILE:
                try:
                    unpack(path, item.unpack, item.member, work)
                except _BadArchive as exc:
                    path.unlink(missing_ok=True)
                    raise VPRInputError(f"{exc} (the downloaded file was deleted)") from None
        root = _single_folder(work)
        for item, path in zip(dataset.downloads, files):
            if item.unpack is Unpack.FILE:
                shutil.copyfile(path, root / item.place_as)
        try:
            _check_layout(root, dataset)
        except VPRInputError as exc:
            raise VPRInputError(f"{exc} (the downloads are kept in {downloads}, to look at)") from None
        os.rename(root, target)
    except OSError as exc:
        raise VPRInputError(f"{target}: cannot write the dataset ({exc.strerror}: {exc.filename}); free some space or "
                            "pick another --to folder") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for path in files:
        path.unlink(missing_ok=True)
    return FetchResult(path=target, skipped=False, digests=tuple(digests))

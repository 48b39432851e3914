"""The catalogue, and fetching against a real HTTP server on 127.0.0.1: resume, checksums, safe unpacking, no debris.

A ``ThreadingHTTPServer`` on a free port serves archives built here (tiny GardensPoint-shaped
traversals, a database/queries set with ``@east@north@`` names), honouring ``Range`` unless
told not to, and can drop the connection after N bytes. Every failure must be one
``VPRInputError`` naming the URL or file, with no dataset folder and no temporary folder
left behind. Nothing here reaches beyond 127.0.0.1.
"""

from __future__ import annotations

import hashlib
import io
import re
import socket
import tarfile
import threading
import zipfile
from dataclasses import replace
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from PIL import Image

from cli_run import assert_one_error_line, refused, run
from test_app import fresh_caches, navigation_mode  # noqa: F401  (autouse fixtures the AppTest below needs)
from vpr_explorer.data.catalogue import BY_NAME, CATALOGUE, Access, Download, PublicDataset, Unpack, find
from vpr_explorer.data.fetch import DOWNLOADS, MIRROR_ENV, data_folder, fetch, url_of
from vpr_explorer.data.layouts import Layout, detect_layout, load_retrieval
from vpr_explorer.data.traversals import load_traversal_folders
from vpr_explorer.errors import VPRInputError

TRAVERSALS = ("day_left", "day_right", "night_right")
FRAMES = 3


# --------------------------------------------------------------------------- the server


class Handler(BaseHTTPRequestHandler):
    """Serves ``server.files`` by path; ``server.ignore_range`` and ``server.drop_after`` (bytes, once) alter it."""

    protocol_version = "HTTP/1.1"

    def log_message(self, *args) -> None:  # quiet
        pass

    def do_GET(self) -> None:
        srv = self.server
        srv.seen.append((self.path, self.headers.get("Range")))
        body = srv.files.get(self.path.split("?")[0])
        if body is None:
            self.send_error(404, "Not Found")
            return
        start = 0
        match = re.fullmatch(r"bytes=(\d+)-", self.headers.get("Range") or "")
        if match and not srv.ignore_range:
            start = int(match[1])
            if start >= len(body):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(body)}")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        else:
            self.send_response(200)
        self.send_header("Content-Length", str(len(body) - start))
        self.end_headers()
        drop = srv.drop_after.pop(self.path, None)
        if drop is not None:
            self.wfile.write(body[start:start + drop])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(socket.SHUT_RDWR)
            return
        self.wfile.write(body[start:])


@pytest.fixture
def server():
    """A live server: ``server.files[path] = bytes``; ``server.url`` its base; ``server.seen`` (path, Range) requests."""
    srv = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    srv.files, srv.seen, srv.drop_after, srv.ignore_range = {}, [], {}, False
    srv.url = f"http://127.0.0.1:{srv.server_address[1]}"
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def closed_port() -> int:
    """A port on 127.0.0.1 nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- archives


def image_bytes(i: int, fmt: str = "PNG") -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (8, 6), (40 * i % 256, 90, 200 - 20 * i % 200)).save(buf, format=fmt)
    return buf.getvalue()


def traversal_files(prefix: str) -> dict[str, bytes]:
    """A GardensPoint-shaped tree: three traversals of FRAMES JPEG frames under ``prefix``."""
    return {f"{prefix}/{t}/Image{f:03d}.jpg": image_bytes(3 * k + f, "JPEG")
            for k, t in enumerate(TRAVERSALS) for f in range(FRAMES)}


def database_queries_files(top: str = "Tiny") -> dict[str, bytes]:
    """Four database and two query PNGs named ``@east@north@…``, 10 m apart along a line, under one folder."""
    files = {f"{top}/database/@{500000 + 10 * i}@{4000000}@55@H@@@@@@@@@@@.png": image_bytes(i) for i in range(4)}
    files.update({f"{top}/queries/@{500001 + 20 * i}@{4000000}@55@H@@@@@@@@@@@.png": image_bytes(7 + i)
                  for i in range(2)})
    return files


def tar_gz(files: dict[str, bytes], extra: list[tarfile.TarInfo] = ()) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, data in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        for info in extra:
            tar.addfile(info)
    return buf.getvalue()


def zip_bytes(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(zipfile.ZipInfo(name), data)
    return buf.getvalue()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def zip_dataset(sha256: str | None = None, file_name: str = "tiny.zip", **fields) -> PublicDataset:
    """A database/queries dataset of one zip, for the tests (not in the catalogue)."""
    return PublicDataset(
        name="tiny", title="Tiny", home="http://127.0.0.1/", licence="test", size="6 images",
        layout=Layout.DATABASE_QUERIES, access=Access.DOWNLOAD, folder="Tiny",
        downloads=(Download(url="http://127.0.0.1:9/never", file_name=file_name, sha256=sha256),), **fields)


def leftovers(to: Path) -> list[str]:
    """Everything in the data folder but the downloads folder's ``.part`` files."""
    found = [p.name for p in to.iterdir() if p.name != DOWNLOADS] if to.is_dir() else []
    if (to / DOWNLOADS).is_dir():
        found += [p.name for p in (to / DOWNLOADS).iterdir() if not p.name.endswith(".part")]
    return found


GP = BY_NAME["gardens-point-walking"]
GP_PREFIX = GP.downloads[0].member


def serve_gardens_point(server) -> bytes:
    """The catalogue's GardensPoint archive as GitHub shapes it: the repository's tree, the dataset in a sub-folder."""
    files = traversal_files(GP_PREFIX)
    top = GP_PREFIX.split("/")[0]
    files[f"{top}/README.md"] = b"the rest of the repository"
    files[f"{top}/place-recognition/model.txt"] = b"not part of the dataset"
    data = tar_gz(files)
    server.files["/" + GP.downloads[0].file_name] = data
    return data


# --------------------------------------------------------------------------- the catalogue


def test_catalogue_entries_are_complete_and_consistent():
    names = [d.name for d in CATALOGUE]
    assert len(set(names)) == len(names)
    files = [f.file_name for d in CATALOGUE for f in d.downloads]
    assert len(set(files)) == len(files), "a mirror serves every file by its name: names must differ"
    for d in CATALOGUE:
        assert re.fullmatch(r"[a-z0-9]+(-[a-z0-9]+)*", d.name), d.name
        assert d.home.startswith(("https://", "http://")) and d.licence and d.size and d.folder
        assert isinstance(d.layout, Layout) and d.layout is not Layout.AUTO
        if d.access is Access.DOWNLOAD:
            assert d.downloads and not d.how
            assert d.downloads[0].unpack in (Unpack.ZIP, Unpack.TAR_GZ)
            for f in d.downloads:
                assert f.url.startswith("https://"), f.url
                assert f.sha256 is None or re.fullmatch(r"[0-9a-f]{64}", f.sha256)
                assert (f.unpack is Unpack.FILE) == bool(f.place_as)
        else:
            assert not d.downloads and d.how, d.name


def test_catalogue_holds_the_datasets_the_explorer_uses():
    for name in ("gardens-point-walking", "nordland-64x32", "nordland", "st-lucia", "vpr-bench-corridor",
                 "vpr-bench-spedtest", "vpr-bench-nordland", "eynsham", "pitts30k", "tokyo247", "msls"):
        assert name in BY_NAME
    # the folders of the copies in shared/datasets, so $VPR_EXPLORER_DATA/<folder> is the same dataset
    assert BY_NAME["gardens-point-walking"].folder == "GardensPointWalking"
    assert BY_NAME["nordland-64x32"].folder == "Nordland_64x32"
    assert BY_NAME["nordland-64x32"].layout is Layout.TRAVERSALS
    for d in CATALOGUE:
        if d.name.startswith("vpr-bench-") and d.name != "vpr-bench-corridor":
            gt = d.downloads[1]
            assert d.layout is Layout.VPR_BENCH and gt.place_as == "ground_truth_new.npy" and gt.sha256
            assert "/77ad30f3684476717188c67d7f3f66be19f832af/" in gt.url
    assert {d.access for d in CATALOGUE} == set(Access)


def test_find_reads_names_loosely_and_lists_them_when_unknown():
    assert find("Nordland_64x32") is BY_NAME["nordland-64x32"]
    with pytest.raises(VPRInputError, match="not in the catalogue.*gardens-point-walking"):
        find("kitti")


def test_checksums_summary_and_mirror_urls():
    assert GP.checksums == "not published"
    assert BY_NAME["vpr-bench-spedtest"].checksums == "partly"
    assert BY_NAME["st-lucia"].checksums == "-"
    assert url_of(GP.downloads[0]) == GP.downloads[0].url
    assert url_of(GP.downloads[0], "http://m/x/") == f"http://m/x/{GP.downloads[0].file_name}"


def test_data_folder_default(monkeypatch, tmp_path):
    assert data_folder({"VPR_EXPLORER_DATA": str(tmp_path)}) == tmp_path
    assert data_folder({}) == Path("~/vpr-data").expanduser()


# --------------------------------------------------------------------------- fetch


def test_good_archive_is_fetched_unpacked_and_opens(server, tmp_path):
    data = serve_gardens_point(server)
    result = fetch(GP, tmp_path, mirror=server.url)
    assert not result.skipped and result.path == tmp_path / "GardensPointWalking"
    ds = load_traversal_folders(result.path)
    assert ds.traversals == TRAVERSALS and ds.n_frames == FRAMES
    assert sorted(p.name for p in result.path.iterdir()) == sorted(TRAVERSALS)  # the rest of the repository left out
    assert (result.digests[0].sha256, result.digests[0].checked) == (sha(data), False)
    assert leftovers(tmp_path) == ["GardensPointWalking"] and not list((tmp_path / DOWNLOADS).iterdir())


def test_checksum_checked_and_retrieval_layout_opens(server, tmp_path):
    data = zip_bytes(database_queries_files())
    server.files["/tiny.zip"] = data
    result = fetch(zip_dataset(sha(data)), tmp_path, mirror=server.url)
    assert result.digests[0].checked
    assert detect_layout(result.path) is Layout.DATABASE_QUERIES
    ds = load_retrieval(result.path, Layout.DATABASE_QUERIES)
    assert (ds.n_database, ds.n_queries) == (4, 2)
    # query 0 at east 500001 lies within 25 m of database images at 0, 10, 20 m; query 1 at 21 m of 10, 20, 30 m
    assert [sorted(ds.ground_truth.positives(q)) for q in range(2)] == [[0, 1, 2], [0, 1, 2, 3]]


def test_a_given_sha256_is_checked(server, tmp_path):
    data = serve_gardens_point(server)
    assert fetch(GP, tmp_path, mirror=server.url, sha256=sha(data).upper()).digests[0].checked
    with pytest.raises(VPRInputError, match="64 hexadecimal"):
        fetch(GP, tmp_path / "other", mirror=server.url, sha256="abc")


def test_wrong_checksum_deletes_the_file_and_leaves_nothing(server, tmp_path):
    server.files["/tiny.zip"] = zip_bytes(database_queries_files())
    with pytest.raises(VPRInputError, match=rf"{server.url}/tiny.zip: sha256 [0-9a-f]{{64}} differs from the "
                                            rf"expected {'0' * 64}; the file was deleted"):
        fetch(zip_dataset("0" * 64), tmp_path, mirror=server.url)
    assert leftovers(tmp_path) == [] and not list((tmp_path / DOWNLOADS).iterdir())


def test_truncated_archive_is_one_error_and_no_folder(server, tmp_path):
    data = zip_bytes(database_queries_files())
    server.files["/tiny.zip"] = data[: len(data) // 2]  # served whole: the archive itself is cut
    with pytest.raises(VPRInputError, match=r"tiny.zip: the archive is damaged or truncated .*run the same command "
                                            r"again to fetch it afresh \(the downloaded file was deleted\)"):
        fetch(zip_dataset(), tmp_path, mirror=server.url)
    assert leftovers(tmp_path) == []
    server.files["/cut.tar.gz"] = serve_gardens_point(server)[:300]
    with pytest.raises(VPRInputError, match="damaged or truncated"):
        fetch(replace(GP, downloads=(replace(GP.downloads[0], file_name="cut.tar.gz"),)), tmp_path, mirror=server.url)
    assert leftovers(tmp_path) == []


def test_dropped_connection_keeps_the_part_and_the_next_run_resumes_with_range(server, tmp_path):
    data = serve_gardens_point(server)
    path = "/" + GP.downloads[0].file_name
    cut = len(data) // 3
    server.drop_after[path] = cut
    with pytest.raises(VPRInputError, match=rf"{re.escape(server.url + path)}: the download stopped after "
                                            rf"{cut:,} of {len(data):,} bytes .*kept in .*\.part: run the same command "
                                            "again to resume"):
        fetch(GP, tmp_path, mirror=server.url)
    part = tmp_path / DOWNLOADS / f"{GP.downloads[0].file_name}.part"
    assert part.read_bytes() == data[:cut] and leftovers(tmp_path) == []
    result = fetch(GP, tmp_path, mirror=server.url, sha256=sha(data))
    assert server.seen[-1] == (path, f"bytes={cut}-")
    assert result.digests[0].checked and load_traversal_folders(result.path).n_images == 3 * FRAMES
    assert not part.exists()


def test_server_that_ignores_range_restarts_cleanly(server, tmp_path):
    data = zip_bytes(database_queries_files())
    server.files["/tiny.zip"], server.ignore_range = data, True
    part = tmp_path / DOWNLOADS / "tiny.zip.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(b"stale bytes of another download")
    result = fetch(zip_dataset(sha(data)), tmp_path, mirror=server.url)
    assert server.seen[-1] == ("/tiny.zip", f"bytes={len(b'stale bytes of another download')}-")
    assert result.digests[0].checked and load_retrieval(result.path, Layout.DATABASE_QUERIES).n_images == 6


def test_a_complete_part_answered_416_is_used(server, tmp_path):
    data = zip_bytes(database_queries_files())
    server.files["/tiny.zip"] = data
    part = tmp_path / DOWNLOADS / "tiny.zip.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(data)
    assert fetch(zip_dataset(sha(data)), tmp_path, mirror=server.url).digests[0].checked


def test_unreachable_host_and_http_error(server, tmp_path):
    url = f"http://127.0.0.1:{closed_port()}"
    with pytest.raises(VPRInputError, match=rf"{url}/tiny.zip: cannot connect .*--from URL"):
        fetch(zip_dataset(), tmp_path, mirror=url, timeout=5)
    with pytest.raises(VPRInputError, match=rf"{server.url}/tiny.zip: HTTP 404"):
        fetch(zip_dataset(), tmp_path, mirror=server.url)
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("kind", ["tar-dotdot", "zip-dotdot", "tar-absolute", "zip-absolute", "tar-symlink",
                                  "tar-device"])
def test_unsafe_members_are_refused_and_nothing_is_written_outside(server, tmp_path, kind):
    to = tmp_path / "data"
    evil = tmp_path / "evil"
    files = database_queries_files()
    extra = []
    if kind.endswith("dotdot"):
        files["Tiny/../../evil"] = b"x"
    elif kind.endswith("absolute"):
        files[str(evil)] = b"x"
    elif kind == "tar-symlink":
        link = tarfile.TarInfo("Tiny/database/escape")
        link.type, link.linkname = tarfile.SYMTYPE, "../../../evil"
        extra = [link]
    else:
        dev = tarfile.TarInfo("Tiny/dev")
        dev.type = tarfile.CHRTYPE
        extra = [dev]
    is_zip = kind.startswith("zip")
    name = "tiny.zip" if is_zip else "tiny.tar.gz"
    server.files["/" + name] = zip_bytes(files) if is_zip else tar_gz(files, extra)
    dataset = zip_dataset(file_name=name)
    if not is_zip:
        dataset = replace(dataset, downloads=(replace(dataset.downloads[0], unpack=Unpack.TAR_GZ),))
    with pytest.raises(VPRInputError, match=rf"{name}: member .* is refused \(.*\); nothing was extracted"):
        fetch(dataset, to, mirror=server.url)
    assert not evil.exists() and leftovers(to) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_unpacked_folder_of_the_wrong_layout_is_not_kept(server, tmp_path):
    server.files["/tiny.zip"] = zip_bytes(traversal_files("Tiny"))
    with pytest.raises(VPRInputError, match="unpacked into a traversals folder .* not the database-queries layout the catalogue expects; "
                                            "nothing was kept .the downloads are kept in .*, to look at"):
        fetch(zip_dataset(), tmp_path, mirror=server.url)
    assert leftovers(tmp_path) == ["tiny.zip"]  # the archive, to look at; no dataset folder, no temporary folder


def test_existing_target_is_skipped_without_a_request(server, tmp_path):
    (tmp_path / "GardensPointWalking").mkdir()
    (tmp_path / "GardensPointWalking" / "mine.txt").write_text("kept")
    result = fetch(GP, tmp_path, mirror=server.url)
    assert result.skipped and result.digests == () and server.seen == []
    assert (tmp_path / "GardensPointWalking" / "mine.txt").read_text() == "kept"


def test_rsync_script_and_request_datasets_are_refused_by_name(tmp_path):
    for name in ("nordland", "san-francisco", "pitts30k"):
        with pytest.raises(VPRInputError, match=rf"dataset '{name}' .*: {re.escape(BY_NAME[name].how[:30])}"):
            fetch(BY_NAME[name], tmp_path)
    assert leftovers(tmp_path) == []


# --------------------------------------------------------------------------- the command line


def test_cli_datasets_lists_every_entry():
    r = run("datasets")
    assert r.returncode == 0, r.stderr
    listed = {line.split()[0] for line in r.stdout.splitlines()[1:] if line.strip() and not line.startswith(" ")}
    assert {d.name for d in CATALOGUE} <= listed
    assert f"{len(CATALOGUE)} datasets" in r.stdout
    r = run("datasets", "vpr-bench-spedtest", "gardens-point-walking")
    assert r.returncode == 0
    assert "sha256: 4948ed660fb1c95904678c4ddb20b23aa81f1de5faff922c133ad64b116be865" in r.stdout
    assert "sha256: not published" in r.stdout and GP.downloads[0].url in r.stdout


def test_cli_fetch_end_to_end(server, tmp_path):
    data = serve_gardens_point(server)
    r = run("fetch", "gardens-point-walking", "--to", str(tmp_path), "--from", server.url)
    assert r.returncode == 0, r.stderr
    path = tmp_path / "GardensPointWalking"
    assert f"sha256 {sha(data)}  {GP.downloads[0].file_name} (not published, so not verified" in r.stdout
    assert r.stdout.rstrip().endswith(f"--dataset {path}")
    r = run("list", "--dataset", str(path))
    assert r.returncode == 0 and len(r.stdout.split()) == 3 * FRAMES
    r = run("fetch", "gardens-point-walking", "--to", str(tmp_path), "--from", server.url)
    assert r.returncode == 0 and "exists already: not fetched again" in r.stdout


def test_cli_fetch_errors_are_one_line(server, tmp_path, capsys, monkeypatch):
    url = f"http://127.0.0.1:{closed_port()}"
    monkeypatch.setenv(MIRROR_ENV, url)
    line = assert_one_error_line(refused(capsys, "fetch", "nordland-64x32", "--to", str(tmp_path)), "cannot connect",
                                 url, alone=False)
    assert "seqslam-38311ace.tar.gz" in line
    assert_one_error_line(refused(capsys, "fetch", "pitts30k", "--to", str(tmp_path)), "is not public", "ask the "
                          "authors", alone=False)
    assert_one_error_line(refused(capsys, "fetch", "kitti"), "not in the catalogue")
    assert leftovers(tmp_path) == []


# --------------------------------------------------------------------------- the app


def test_app_fetch_panel(server, tmp_path, monkeypatch):
    from streamlit.testing.v1 import AppTest

    from test_app import TIMEOUT
    from vpr_explorer.app import DATA_ROOT_ENV, ENTRY

    serve_gardens_point(server)
    monkeypatch.setenv(DATA_ROOT_ENV, str(tmp_path))
    monkeypatch.setenv(MIRROR_ENV, server.url)
    at = AppTest.from_file(str(ENTRY), default_timeout=TIMEOUT).run()
    assert not at.exception
    at.selectbox(key="w_fetch_name").set_value("gardens-point-walking").run()
    at.button(key="w_fetch").click().run()
    assert not at.exception and not at.error, [e.value for e in at.error]
    assert any("is ready at" in s.value and str(tmp_path / "GardensPointWalking") in s.value for s in at.success)
    assert load_traversal_folders(tmp_path / "GardensPointWalking").n_frames == FRAMES

    server.files.clear()  # the next dataset is missing on the mirror: one st.error, no traceback, no folder
    at.selectbox(key="w_fetch_name").set_value("nordland-64x32").run()
    at.button(key="w_fetch").click().run()
    assert not at.exception
    assert any("HTTP 404" in e.value and "seqslam-38311ace.tar.gz" in e.value for e in at.error)
    assert not (tmp_path / "Nordland_64x32").exists()
    at.selectbox(key="w_fetch_name").set_value("pitts30k").run()
    assert any("ask the authors" in i.value for i in at.info)

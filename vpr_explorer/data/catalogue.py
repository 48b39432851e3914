"""The public VPR datasets the explorer knows: where each lives, under what licence, and how it is fetched.

Plain data, one frozen ``PublicDataset`` per dataset, listed by ``vpr-explorer datasets``
and fetched by ``vpr-explorer fetch NAME`` (``data.fetch``). Each names its public home,
its licence as its sources state it, its size, the ``Layout`` it opens in once fetched,
and how it is obtained (``Access``):

* ``download``: every file is a plain HTTP(S) download (``Download``): an archive to unpack
  (a sub-folder of it kept, where ``member`` names one) and files to place beside it (the
  VPR-Bench ground truth). ``sha256`` is the file's digest where one is known; ``None``
  means none is published, and ``fetch`` prints the digest it got so that it can be pinned.
* ``rsync``: public, but only over rsync (gmberton/VPR-datasets-downloader's server);
  ``how`` is the command. ``fetch`` refuses it by name and prints that command.
* ``script``: public archives that need the downloader's own formatting script (video
  frames, KML routes, many tar files); ``how`` names it.
* ``request``: not public: a form, a licence or an e-mail to the authors; ``how`` says where.

Where each URL and digest comes from (``source``), as read, with nothing made up:

* GardensPoint Walking and Nordland 64×32: the GitHub archive of the commit the copies in
  ``shared/datasets`` were taken from (aghagol/loop-detection ``2efbb768``, TimQuelch/seqslam
  ``38311ace``); their trees were read from those commits (file count and bytes below).
  GitHub does not promise a byte-stable archive, so no digest is given.
* GardensPoint Walking (VPR_Tutorial's zip): the URL stschubert/VPR_Tutorial's
  ``datasets/load_dataset.py`` downloads; VPR_Tutorial reads ``day_right/`` and
  ``night_right/`` from it.
* VPR-Bench: the SURFdrive share of MubarizZaffar/VPR-Bench's README. ``SPEDTEST.zip``
  (gmberton/VPR-datasets-downloader's ``download_sped.py``), ``Nordland.zip`` and
  ``ESSEX3IN1_dataset.zip`` are named by public scripts; the other sets' file names follow
  the share's naming (the set's folder name in VPR-Bench's ``datasets/`` + ``.zip``) and are
  not confirmed. The ground truth ``ground_truth_new.npy`` of every set comes from the
  VPR-Bench repository at commit ``77ad30f3``; its sha256 was computed from that commit's
  blobs, so it is checked. Corridor ships inside that repository.
* gmberton/VPR-datasets-downloader (README at ``2f886d5``): St Lucia, Nordland (the
  Patch-NetVLAD split), Eynsham and Baidu are served over rsync; San Francisco, AmsterTime
  and SVOX by its scripts; Pittsburgh, Tokyo 24/7 and Mapillary SLS on request.

Folder names (``folder``) match ``shared/datasets`` where a copy is kept there, so that
``$VPR_EXPLORER_DATA/GardensPointWalking`` is the same dataset on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from vpr_explorer.data.layouts import Layout, VPR_BENCH_GT
from vpr_explorer.errors import VPRInputError


class Access(StrEnum):
    """How a dataset is obtained."""

    DOWNLOAD = "download"
    RSYNC = "rsync"
    SCRIPT = "script"
    REQUEST = "request"


class Unpack(StrEnum):
    """What ``fetch`` does with a downloaded file."""

    ZIP = "zip"
    TAR_GZ = "tar.gz"
    FILE = "file"  # placed as it is, at ``Download.place_as``


@dataclass(frozen=True)
class Download:
    """One file of a dataset, downloaded over HTTP(S).

    Attributes:
        url: where it is downloaded from.
        file_name: the name it is saved under (and looked up under on a mirror: ``MIRROR/file_name``).
        sha256: its hex digest where one is known; ``None``: not published.
        unpack: an archive to unpack, or a file to place.
        member: the folder inside the archive that is the dataset (``""``: the whole archive;
            an archive holding one folder and nothing else is that folder).
        place_as: a ``FILE``'s path inside the dataset folder.
    """

    url: str
    file_name: str
    sha256: str | None = None
    unpack: Unpack = Unpack.ZIP
    member: str = ""
    place_as: str = ""


@dataclass(frozen=True)
class PublicDataset:
    """One public dataset.

    Attributes:
        name: what ``vpr-explorer fetch`` takes (lower case, ``-``).
        title: its usual name.
        home: its public home (URL).
        licence: as its sources state it.
        size: images and bytes, as measured or published.
        layout: the explorer layout it opens in once fetched.
        access: how it is obtained.
        folder: the folder ``fetch`` writes under the data folder.
        downloads: the files of a ``download`` dataset, archive first.
        how: what to do for the other kinds (the rsync command, the script, whom to ask).
        source: where the URLs and digests were read.
    """

    name: str
    title: str
    home: str
    licence: str
    size: str
    layout: Layout
    access: Access
    folder: str
    downloads: tuple[Download, ...] = ()
    how: str = ""
    source: str = ""

    @property
    def checksums(self) -> str:
        """``"checked"``, ``"partly"`` (some files have a digest) or ``"not published"``."""
        known = [d.sha256 is not None for d in self.downloads]
        if not known:
            return "-"
        return "checked" if all(known) else "partly" if any(known) else "not published"


_LOOP_DETECTION = "2efbb768787235a4a020d6b27ca0a1761beb515d"
_SEQSLAM = "38311ace3bec3f4acec10c684fd81e28d02143fd"
_VPR_BENCH = "77ad30f3684476717188c67d7f3f66be19f832af"
_SURFDRIVE = "https://surfdrive.surf.nl/files/index.php/s/sbZRXzYe3l0v67W"
_TU_CHEMNITZ = "https://www.tu-chemnitz.de/etit/proaut/datasets/"
_RSYNC = "rsync://vandaldata.polito.it/sf_xl/VPR-datasets-downloader/"
_DOWNLOADER = "https://github.com/gmberton/VPR-datasets-downloader"
_NETVLAD = "https://www.di.ens.fr/willow/research/netvlad/"
_NOT_STATED = "not stated by the sources read; see the home page"
_VPR_BENCH_LICENCE = ("per dataset (VPR-Bench asks users to follow each original licence); ground truth from the "
                      "VPR-Bench repository, MIT")
_DOWNLOADER_SOURCE = f"{_DOWNLOADER} README (commit 2f886d5)"

#: the sha256 of ``ground_truth_new.npy`` in VPR-Bench's ``datasets/<folder>/`` at commit ``_VPR_BENCH``
_VPR_BENCH_GT_SHA256 = {
    "17places": "f59424ca043f5901f66f1222bb0ab06430071452dd477a0e83ef90d56151792d",
    "CrossSeason_CoHOG_Dataset": "179ff3f8138520579745d19e0d9499e703359ebe3db61645bcabd99f61811deb",
    "ESSEX3IN1_dataset": "4d89fb4ff44e7be57c29d9551b4c104182fd22890e215f61a27baeebaf9b11de",
    "GardensPointWalking": "59a2c742386744a2d057c07ed4cd29669ff381d893202afde08eab4ab266d312",
    "GardensPoint_TN": "4cc7a406e5245664d06a26db2fa05232290fcc7b4cc55555b2d034adf15d8fd2",
    "Living": "557adc61ae9fbfc7494da890c4d28d83a3791bd9323ffdf594e003c8a3f73c7e",
    "Nordland": "effb290a44fb4b8f11922303a37831a839f3b59e1ad8c5265e80024791db0a1a",
    "SPEDTEST": "4948ed660fb1c95904678c4ddb20b23aa81f1de5faff922c133ad64b116be865",
    "Synthia-NightToFall": "7991b92643626cdec835dde3d9556b1d8d4198bdec78d5267f4148b26f0f809b",
    "inria_holidays": "08143fc3441b962ba05d838b4e306f973886ce992b9fe70abc360817c2d904b1",
}


def _github_archive(repo: str, commit: str, member: str) -> Download:
    """The ``.tar.gz`` of ``repo`` at ``commit``, keeping the folder ``member`` of its tree."""
    name = repo.split("/")[1]
    return Download(url=f"https://github.com/{repo}/archive/{commit}.tar.gz", file_name=f"{name}-{commit[:8]}.tar.gz",
                    unpack=Unpack.TAR_GZ, member=f"{name}-{commit}/{member}")


def _vpr_bench(name: str, folder: str, title: str, size: str, confirmed: str = "", licence: str = "") -> PublicDataset:
    """A VPR-Bench set: its zip from the SURFdrive share, its ground truth from the repository."""
    named = (f"the zip's name is confirmed by {confirmed}" if confirmed else
             f"the zip's name follows the share's naming ({folder}.zip) and is not confirmed: if it is missing, "
             f"browse {_SURFDRIVE}")
    return PublicDataset(
        name=name, title=title, home=_SURFDRIVE, licence=licence or _VPR_BENCH_LICENCE, size=size,
        layout=Layout.VPR_BENCH, access=Access.DOWNLOAD, folder=f"VPR-Bench_{folder}",
        downloads=(
            Download(url=f"{_SURFDRIVE}/download?path=%2F&files={folder}.zip", file_name=f"{folder}.zip"),
            Download(url=f"https://raw.githubusercontent.com/MubarizZaffar/VPR-Bench/{_VPR_BENCH}/datasets/{folder}/"
                         f"{VPR_BENCH_GT}", file_name=f"{folder}_{VPR_BENCH_GT}", sha256=_VPR_BENCH_GT_SHA256[folder],
                     unpack=Unpack.FILE, place_as=VPR_BENCH_GT),
        ),
        source=f"MubarizZaffar/VPR-Bench README and must_downloads.txt; {named}; ground truth at commit {_VPR_BENCH[:8]}",
    )


def _rsync(name: str, title: str, folder: str, licence: str, size: str, note: str = "") -> PublicDataset:
    """A gmberton/VPR-datasets-downloader set served over rsync, in its ``images/test`` layout."""
    return PublicDataset(
        name=name, title=title, home=_DOWNLOADER, licence=licence, size=size, layout=Layout.DATABASE_QUERIES,
        access=Access.RSYNC, folder=folder,
        how=(f"rsync -rhz --info=progress2 --ignore-existing {_RSYNC}{folder} \"$VPR_EXPLORER_DATA/\"; then open "
             f"--dataset \"$VPR_EXPLORER_DATA/{folder}\"" + (f" ({note})" if note else "")),
        source=_DOWNLOADER_SOURCE,
    )


CATALOGUE: tuple[PublicDataset, ...] = (
    PublicDataset(
        name="gardens-point-walking", title="GardensPoint Walking", home="https://doi.org/10.5281/zenodo.4590133",
        licence=_NOT_STATED + " (Zenodo record 4590133); the repository carrying this copy has no licence file",
        size="600 images (day_left, day_right, night_right × 200); the archive is the whole repository: 628 files, "
             "32.5 MB before compression",
        layout=Layout.TRAVERSALS, access=Access.DOWNLOAD, folder="GardensPointWalking",
        downloads=(_github_archive("aghagol/loop-detection", _LOOP_DETECTION, "PR_bench/GardensPointWalking"),),
        source=f"github.com/aghagol/loop-detection, commit {_LOOP_DETECTION[:8]}, PR_bench/GardensPointWalking "
               "(the copy in shared/datasets)",
    ),
    PublicDataset(
        name="gardens-point-walking-vpr-tutorial", title="GardensPoint Walking (VPR_Tutorial's zip)",
        home="https://github.com/stschubert/VPR_Tutorial", licence=_NOT_STATED + " (Zenodo record 4590133)",
        size="not published (VPR_Tutorial reads day_right/ and night_right/, 200 images each)",
        layout=Layout.TRAVERSALS, access=Access.DOWNLOAD, folder="GardensPoint_Walking",
        downloads=(Download(url=_TU_CHEMNITZ + "GardensPoint_Walking.zip", file_name="GardensPoint_Walking.zip"),),
        source="stschubert/VPR_Tutorial datasets/load_dataset.py (GardensPointDataset.download)",
    ),
    PublicDataset(
        name="nordland-64x32", title="Nordland, 64×32 greyscale (OpenSeqSLAM export, every 10th frame)",
        home="https://github.com/TimQuelch/seqslam", licence="CC BY 3.0 (footage: NRK)",
        size="7,152 images (summer, winter × 3,576), 64×32 PNG; the archive is the whole repository: 14,355 files, "
             "26.2 MB before compression",
        layout=Layout.TRAVERSALS, access=Access.DOWNLOAD, folder="Nordland_64x32",
        downloads=(_github_archive("TimQuelch/seqslam", _SEQSLAM, "datasets/nordland_trimmed"),),
        source=f"github.com/TimQuelch/seqslam, commit {_SEQSLAM[:8]}, datasets/nordland_trimmed "
               "(the copy in shared/datasets)",
    ),
    PublicDataset(
        name="vpr-bench-corridor", title="Corridor (VPR-Bench)",
        home="https://github.com/MubarizZaffar/VPR-Bench/tree/master/datasets/corridor", licence=_VPR_BENCH_LICENCE,
        size="111 reference and 111 query images; the archive is the whole VPR-Bench repository (38 MB before "
             "compression)",
        layout=Layout.VPR_BENCH, access=Access.DOWNLOAD, folder="VPR-Bench_corridor",
        downloads=(_github_archive("MubarizZaffar/VPR-Bench", _VPR_BENCH, "datasets/corridor"),),
        source=f"MubarizZaffar/VPR-Bench, commit {_VPR_BENCH[:8]}, datasets/corridor (ref/, query/, {VPR_BENCH_GT})",
    ),
    _vpr_bench("vpr-bench-spedtest", "SPEDTEST", "SPEDTest (VPR-Bench)", "607 queries; archive size not published",
               confirmed="gmberton/VPR-datasets-downloader download_sped.py"),
    _vpr_bench("vpr-bench-nordland", "Nordland", "Nordland (VPR-Bench's 2,760 queries)",
               "2,760 queries; archive size not published", confirmed="a public download script",
               licence="CC BY 3.0 (footage: NRK); ground truth from the VPR-Bench repository, MIT"),
    _vpr_bench("vpr-bench-essex3in1", "ESSEX3IN1_dataset", "ESSEX3IN1 (VPR-Bench)",
               "210 queries; archive size not published", confirmed="a public download script"),
    _vpr_bench("vpr-bench-gardens-point", "GardensPointWalking", "GardensPoint Walking (VPR-Bench)",
               "200 queries; archive size not published"),
    _vpr_bench("vpr-bench-gardens-point-tn", "GardensPoint_TN", "GardensPoint with true negatives (VPR-Bench)",
               "400 queries; archive size not published"),
    _vpr_bench("vpr-bench-17places", "17places", "17 Places (VPR-Bench)", "406 queries; archive size not published"),
    _vpr_bench("vpr-bench-cross-seasons", "CrossSeason_CoHOG_Dataset", "Cross-Seasons (VPR-Bench)",
               "191 queries; archive size not published"),
    _vpr_bench("vpr-bench-living-room", "Living", "Living Room (VPR-Bench)", "32 queries; archive size not published"),
    _vpr_bench("vpr-bench-synthia", "Synthia-NightToFall", "Synthia night to fall (VPR-Bench)",
               "813 queries; archive size not published",
               licence="CC BY-NC-SA 3.0; ground truth from the VPR-Bench repository, MIT"),
    _vpr_bench("vpr-bench-inria-holidays", "inria_holidays", "INRIA Holidays (VPR-Bench)",
               "300 queries; archive size not published"),
    _rsync("st-lucia", "St Lucia (VPR-datasets-downloader)", "st_lucia", _NOT_STATED, "not published",
           "database: the first pass, queries: the last, frames at least 5 m apart"),
    _rsync("nordland", "Nordland, full size (VPR-datasets-downloader, Patch-NetVLAD split)", "nordland",
           "CC BY 3.0 (footage: NRK)", "not published", "summer database, winter queries; names carry a position "
           "2.38 m per frame, so 25 m is 10 frames"),
    _rsync("eynsham", "Eynsham (VPR-datasets-downloader)", "eynsham", _NOT_STATED, "not published"),
    _rsync("baidu", "Baidu Mall (VPR-datasets-downloader)", "baidu", _NOT_STATED, "not published"),
    PublicDataset(
        name="san-francisco", title="San Francisco Landmark (VPR-datasets-downloader)",
        home="https://stacks.stanford.edu/file/druid:vn158kj2087/", licence=_NOT_STATED,
        size="139 tar files of panoramas and a query zip; not published", layout=Layout.DATABASE_QUERIES,
        access=Access.SCRIPT, folder="san_francisco",
        how=f"run download_san_francisco.py of {_DOWNLOADER} (it downloads and formats the tar files and the poses), "
            "then open --dataset DIR/datasets/san_francisco",
        source=_DOWNLOADER_SOURCE + " and download_san_francisco.py",
    ),
    PublicDataset(
        name="amstertime", title="AmsterTime (VPR-datasets-downloader)",
        home="https://data.4tu.nl/ndownloader/items/d2ee2551-986a-46bc-8540-b43f5b01ec4d/versions/4",
        licence=_NOT_STATED, size="not published", layout=Layout.DATABASE_QUERIES, access=Access.SCRIPT,
        folder="amstertime",
        how=f"run download_amstertime.py of {_DOWNLOADER} (it pairs the archive's images into database/queries), "
            "then open --dataset DIR/datasets/amstertime",
        source=_DOWNLOADER_SOURCE + " and download_amstertime.py",
    ),
    PublicDataset(
        name="svox", title="SVOX (VPR-datasets-downloader)", home=_DOWNLOADER, licence=_NOT_STATED,
        size="not published", layout=Layout.DATABASE_QUERIES, access=Access.SCRIPT, folder="svox",
        how=f"run download_svox.py of {_DOWNLOADER} (a Google Drive file, fetched with gdown), then open the "
            "condition's folder under DIR/datasets/svox/images/test",
        source=_DOWNLOADER_SOURCE + " and download_svox.py",
    ),
    PublicDataset(
        name="pitts30k", title="Pittsburgh 30k", home=_NETVLAD, licence="on request from the authors",
        size="not published", layout=Layout.DATABASE_QUERIES, access=Access.REQUEST, folder="pitts30k",
        how=f"ask the authors for the images (see {_NETVLAD}), then format them with format_pitts30k.py of "
            f"{_DOWNLOADER}",
        source=_DOWNLOADER_SOURCE,
    ),
    PublicDataset(
        name="pitts250k", title="Pittsburgh 250k", home=_NETVLAD, licence="on request from the authors",
        size="not published", layout=Layout.DATABASE_QUERIES, access=Access.REQUEST, folder="pitts250k",
        how=f"ask the authors for the images (see {_NETVLAD}), then format them with format_pitts250k.py of "
            f"{_DOWNLOADER}",
        source=_DOWNLOADER_SOURCE,
    ),
    PublicDataset(
        name="tokyo247", title="Tokyo 24/7", home="http://www.ok.ctrl.titech.ac.jp/~torii/project/247/",
        licence="on request from the authors", size="not published", layout=Layout.DATABASE_QUERIES,
        access=Access.REQUEST, folder="tokyo247",
        how=f"ask the authors for the database images (see the home page), then run format_tokyo247.py of "
            f"{_DOWNLOADER} (it downloads the queries)",
        source=_DOWNLOADER_SOURCE,
    ),
    PublicDataset(
        name="msls", title="Mapillary Street-Level Sequences", home="https://www.mapillary.com/dataset/places",
        licence="Mapillary's terms, accepted at download (log-in)", size="not published",
        layout=Layout.DATABASE_QUERIES, access=Access.REQUEST, folder="mapillary_sls",
        how=f"log in at https://www.mapillary.com/dataset/places, download and unzip it, then run format_mapillary.py "
            f"of {_DOWNLOADER}",
        source=_DOWNLOADER_SOURCE,
    ),
)

BY_NAME: dict[str, PublicDataset] = {d.name: d for d in CATALOGUE}


def find(name: str) -> PublicDataset:
    """The catalogue's dataset called ``name`` (case-insensitive; ``_`` read as ``-``).

    Raises:
        VPRInputError: no dataset has that name; the message lists them.
    """
    key = name.strip().lower().replace("_", "-")
    if key in BY_NAME:
        return BY_NAME[key]
    raise VPRInputError(f"dataset {name!r}: not in the catalogue; `vpr-explorer datasets` lists them: "
                        f"{', '.join(BY_NAME)}")

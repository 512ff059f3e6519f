"""Reading 4D voxel phantoms: XCAT attenuation frames with their log, or a table of NIfTI volumes.

Two formats (``docs/voxel-phantoms.md`` has the full description and the conventions):

**XCAT** (``format = "xcat"``): the files the XCAT program writes for an attenuation run,
``<name>_atn_1.bin``, ``<name>_atn_2.bin``, ... (frames numbered from 1) next to the text file
``<name>_log``. Each frame is raw float32 of ``n_slices x array_size x array_size`` values in
slice, row, column order (column fastest), in the byte order the scene states
(``byte_order``, default little-endian, which is what XCAT writes on x86; a frame whose values
only make sense in the other byte order is an error that says so). Values are linear
attenuation coefficients in 1/pixel (XCAT's unit), converted to 1/mm by dividing by the pixel
width in mm. :func:`parse_xcat_log` reads these lines of the log, each by a
case-insensitive regular expression on one line (``NUM`` is a decimal number; the first
occurrence counts; everything else in the log is ignored):

=========================  ================================================  ========
field                      line                                              needed
=========================  ================================================  ========
pixel width                ``pixel width = NUM (cm/pixel)`` (unit cm unless   yes
                           the line says mm; a line with "voxel volume" is
                           not it)
slice width                ``slice width = NUM (cm/pixel)``                  yes
array size                 ``array_size = INT``                              yes
start and end slice        ``starting slice number = INT``,                  yes
                           ``ending slice number = INT`` (also
                           ``startslice``/``endslice``); slices = end -
                           start + 1
frames                     ``Total Output Frames = INT`` or                  no (else: the
                           ``out_frames = INT``                              files present)
time per frame             ``Time Per Frame = NUM`` (s) or                   for timing
                           ``time_per_frame = NUM``                          "scene"/"xcat"
heart, breathing period    ``hrt_period = NUM``, ``resp_period = NUM`` (s)   for timing "xcat"
start phases               ``hrt_start_ph_index = NUM``,                     no (0)
                           ``resp_start_ph_index = NUM`` (in [0, 1])
attenuation tables         the ``name = NUM`` lines after the header line    the water line
                           ``Linear Attenuation Coefficients (1/pixel):``
                           (and ``(1/cm):``), up to the first line that is
                           not ``name = NUM``; water is ``Body (water)``
=========================  ================================================  ========

When both tables hold ``Body (water)``, they must agree with the pixel width
(``mu_cm * width_cm = mu_pixel`` within 1 %, the log's rounding): this catches a pixel
width read in the wrong unit.

Orientation (the log does not state it; our reading, also a scene key): a slice's rows run
anterior to posterior (+y of LPS) and its columns patient right to left (+x), the radiological
display XCAT slices are viewed in; slice numbers increase towards ``slice_direction``
(default ``"superior"``: the first slice is the most inferior). XCAT frames carry no world
position: the volume's centre is put at ``centre_mm``.

**NIfTI** (``format = "nifti"``): a table, TOML (``[[frame]]`` entries) or CSV (a header
row), of NIfTI-1/2 files, one 3D volume each, with ``file`` (relative to the table's
folder) and either ``cardiac_phase`` and ``resp_amplitude`` or ``time_s`` (or all three).
Values are HU or mu in 1/mm (scene key ``values``); HU become ``mu_w (1 + HU/1000)``, clipped
at 0 (no negative attenuation). Geometry comes from each file's affine (nibabel's best
affine, sform before qform), which maps voxel indices to RAS+ mm; LPS = diag(-1, -1, 1) RAS.
Only affines whose axes are parallel to the LPS axes (any permutation and signs) are read;
the volume is transposed and flipped to ``mu[z, y, x]`` with increasing coordinates. Every
frame must have the first frame's shape, spacing and origin.

Frames are read lazily (``np.memmap`` for XCAT, nibabel's array proxy for NIfTI) and at
most :data:`FRAME_CACHE_SIZE` converted frames are held in memory at a time, whatever the
number of phantoms or scenes: an XCAT series of 50 frames of 512^2 x 300 (15 GiB) is
streamed.
"""

from __future__ import annotations

import csv
import hashlib
import math
import re
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clrecon.core.conventions import MU_WATER_PER_MM
from clrecon.core.errors import SceneError

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

#: converted frames held in memory at once (over every phantom source of the process)
FRAME_CACHE_SIZE = 2
#: relative tolerance of the cross-check of the 1/cm and 1/pixel water coefficients
WATER_TABLE_RTOL = 0.01
#: a plausible linear attenuation is below this multiple of water (steel is ~34 x water)
MAX_MU_OVER_WATER = 1000.0

_NUM = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
_INT = r"([-+]?\d+)"


# ---------------------------------------------------------------------------------------
# XCAT log
@dataclass(frozen=True)
class XcatLog:
    """What :func:`parse_xcat_log` read from an XCAT log (lengths in mm, times in s).

    ``mu_water_per_pixel`` is ``Body (water)`` of the 1/pixel table; ``atten_per_pixel`` and
    ``atten_per_cm`` the whole tables (name -> value); ``n_frames``, ``time_per_frame_s``,
    ``hrt_period_s``, ``resp_period_s`` are None where the log has no such line.
    """

    path: Path
    stem: str
    pixel_width_mm: float
    slice_width_mm: float
    array_size: int
    start_slice: int
    end_slice: int
    mu_water_per_pixel: float
    n_frames: int | None = None
    time_per_frame_s: float | None = None
    hrt_period_s: float | None = None
    resp_period_s: float | None = None
    hrt_start_phase: float = 0.0
    resp_start_phase: float = 0.0
    atten_per_pixel: dict = field(default_factory=dict)
    atten_per_cm: dict = field(default_factory=dict)

    @property
    def n_slices(self) -> int:
        return self.end_slice - self.start_slice + 1

    @property
    def mu_water_per_mm(self) -> float:
        return self.mu_water_per_pixel / self.pixel_width_mm

    def frame_path(self, k: int) -> Path:
        """The attenuation frame ``k`` (1-based): ``<stem>_atn_<k>.bin`` beside the log."""
        return self.path.parent / f"{self.stem}_atn_{k}.bin"


def _length_mm(value: float, rest: str) -> float:
    unit = rest.lower()
    return value if re.search(r"\bmm\b", unit) else value * 10.0


def parse_xcat_log(path) -> XcatLog:
    """Parse an XCAT log file (the fields in the module docstring); SceneError naming the file.

    The stem (``<name>`` of the frame files) is the log's name without a trailing ``_log``
    or ``.log``.
    """
    p = Path(path)
    try:
        text = p.read_text(errors="replace")
    except OSError as e:
        raise SceneError(f"XCAT log {p}: cannot be read ({e.strerror or e})") from None
    first: dict = {}
    tables: dict = {"pixel": {}, "cm": {}}
    table = None

    def put(key, value):
        first.setdefault(key, value)

    patterns = [
        ("pixel_width", rf"^\s*pixel[ _]width\s*[=:]\s*{_NUM}(.*)$", float),
        ("slice_width", rf"^\s*slice[ _]width\s*[=:]\s*{_NUM}(.*)$", float),
        ("array_size", rf"^\s*array[ _]size\s*[=:]\s*{_INT}", int),
        ("start_slice", rf"^\s*start(?:ing)?[ _]?slice(?:[ _]number)?\s*[=:]\s*{_INT}", int),
        ("end_slice", rf"^\s*end(?:ing)?[ _]?slice(?:[ _]number)?\s*[=:]\s*{_INT}", int),
        ("n_frames", rf"(?:total\s+output\s+frames|^\s*out_frames)\s*[=:]\s*{_INT}", int),
        ("time_per_frame", rf"time[ _]per[ _]frame\s*[=:]\s*{_NUM}", float),
        ("hrt_period", rf"\bhrt_period\s*[=:]\s*{_NUM}", float),
        ("resp_period", rf"\bresp_period\s*[=:]\s*{_NUM}", float),
        ("hrt_start", rf"\bhrt_start_ph_index\s*[=:]\s*{_NUM}", float),
        ("resp_start", rf"\bresp_start_ph_index\s*[=:]\s*{_NUM}", float),
    ]
    compiled = [(k, re.compile(rx, re.IGNORECASE), conv) for k, rx, conv in patterns]
    entry = re.compile(rf"^\s*(.+?)\s*=\s*{_NUM}\s*(?:\S.*)?$")
    for line in text.splitlines():
        low = line.lower()
        if "linear attenuation coefficients" in low:
            table = "pixel" if "1/pixel" in low.replace(" ", "") else ("cm" if "1/cm" in low.replace(" ", "")
                                                                      else None)
            continue
        if table is not None:
            m = entry.match(line)
            if m:
                tables[table].setdefault(m.group(1).strip(), float(m.group(2)))
                continue
            table = None
        if "voxel volume" in low:
            continue
        for key, rx, conv in compiled:
            m = rx.search(line)
            if m:
                val = conv(m.group(1))
                put(key, (val, m.group(2)) if key in ("pixel_width", "slice_width") else val)
    where = f"XCAT log {p}"
    for key, label in (("pixel_width", "pixel width"), ("slice_width", "slice width"), ("array_size", "array_size"),
                       ("start_slice", "starting slice number"), ("end_slice", "ending slice number")):
        if key not in first:
            raise SceneError(f"{where}: no '{label} = ...' line; is this an XCAT log?")
    water = next((v for k, v in tables["pixel"].items() if k.lower().replace(" ", "") == "body(water)"), None)
    if water is None:
        raise SceneError(f"{where}: no 'Body (water) = ...' line in the 'Linear Attenuation Coefficients "
                         f"(1/pixel):' table (needed to convert to HU)")
    pw = _length_mm(*first["pixel_width"])
    sw = _length_mm(*first["slice_width"])
    n, s0, s1 = first["array_size"], first["start_slice"], first["end_slice"]
    for name, val in (("pixel width", pw), ("slice width", sw)):
        if not (math.isfinite(val) and val > 0):
            raise SceneError(f"{where}: {name} = {val} mm: must be > 0")
    if n < 1 or s1 < s0:
        raise SceneError(f"{where}: array_size = {n}, slices {s0}..{s1}: need array_size >= 1 and "
                         f"ending slice >= starting slice")
    if not (math.isfinite(water) and water > 0):
        raise SceneError(f"{where}: Body (water) = {water} /pixel: must be > 0")
    water_cm = next((v for k, v in tables["cm"].items() if k.lower().replace(" ", "") == "body(water)"), None)
    if water_cm is not None and abs(water_cm * pw / 10.0 - water) > WATER_TABLE_RTOL * water:
        raise SceneError(f"{where}: Body (water) is {water_cm} /cm and {water} /pixel, which needs a pixel width of "
                         f"{10 * water / water_cm:.4g} mm, not {pw:.4g} mm; check the pixel width line's unit")
    stem = re.sub(r"(_log|\.log)$", "", p.name)
    nf = first.get("n_frames")
    if nf is not None and nf < 1:
        raise SceneError(f"{where}: Total Output Frames = {nf}: must be >= 1")
    dt = first.get("time_per_frame")
    if dt is not None and not dt > 0:
        raise SceneError(f"{where}: Time Per Frame = {dt}: must be > 0")
    for key in ("hrt_period", "resp_period"):
        if key in first and not first[key] > 0:
            raise SceneError(f"{where}: {key} = {first[key]}: must be > 0")
    return XcatLog(path=p, stem=stem, pixel_width_mm=pw, slice_width_mm=sw, array_size=n, start_slice=s0,
                   end_slice=s1, mu_water_per_pixel=water, n_frames=nf, time_per_frame_s=dt,
                   hrt_period_s=first.get("hrt_period"), resp_period_s=first.get("resp_period"),
                   hrt_start_phase=float(first.get("hrt_start", 0.0)),
                   resp_start_phase=float(first.get("resp_start", 0.0)),
                   atten_per_pixel=dict(tables["pixel"]), atten_per_cm=dict(tables["cm"]))


def xcat_amplitude(phase) -> np.ndarray:
    """Respiratory amplitude of an XCAT breathing phase: ``(1 - cos 2 pi phase) / 2``.

    0 at phase 0 (end-exhale), 1 at phase 0.5 (end-inhale). An approximation: the log does
    not hold XCAT's breathing curve (``docs/voxel-phantoms.md`` "Frame states").
    """
    return 0.5 * (1.0 - np.cos(2.0 * np.pi * np.asarray(phase, np.float64)))


# ---------------------------------------------------------------------------------------
# NIfTI frame table
@dataclass(frozen=True)
class TableRow:
    """One row of a NIfTI frames table; None where the table has no such column."""

    file: Path
    cardiac_phase: float | None
    resp_amplitude: float | None
    time_s: float | None


_COLUMNS = ("file", "cardiac_phase", "resp_amplitude", "time_s")


def _row(entry: dict, base: Path, where: str) -> TableRow:
    unknown = [k for k in entry if k not in _COLUMNS]
    if unknown:
        raise SceneError(f"{where}: unknown column {unknown[0]!r}; columns are {', '.join(_COLUMNS)}")
    f = entry.get("file")
    if not isinstance(f, str) or not f.strip():
        raise SceneError(f"{where}: needs a 'file' (a NIfTI path, relative to the table's folder)")
    vals = {}
    for k in _COLUMNS[1:]:
        v = entry.get(k)
        if v is None or (isinstance(v, str) and not v.strip()):
            vals[k] = None
            continue
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise SceneError(f"{where}: {k} = {v!r}: must be a number") from None
        if not math.isfinite(x):
            raise SceneError(f"{where}: {k} = {v!r}: must be finite")
        vals[k] = x
    c, a = vals["cardiac_phase"], vals["resp_amplitude"]
    if c is not None and not 0 <= c < 1:
        raise SceneError(f"{where}: cardiac_phase = {c}: must be in [0, 1)")
    if a is not None and not 0 <= a <= 1:
        raise SceneError(f"{where}: resp_amplitude = {a}: must be in [0, 1]")
    if (c is None) != (a is None):
        raise SceneError(f"{where}: give both cardiac_phase and resp_amplitude, or neither (then time_s)")
    if c is None and vals["time_s"] is None:
        raise SceneError(f"{where}: needs cardiac_phase and resp_amplitude, or time_s")
    if vals["time_s"] is not None and vals["time_s"] < 0:
        raise SceneError(f"{where}: time_s = {vals['time_s']}: must be >= 0")
    fp = Path(f.strip())
    return TableRow(file=fp if fp.is_absolute() else base / fp, cardiac_phase=c, resp_amplitude=a,
                    time_s=vals["time_s"])


def parse_frame_table(path) -> list[TableRow]:
    """Rows of a NIfTI frames table (``.toml`` with ``[[frame]]`` entries, or ``.csv`` with a header).

    Columns: ``file`` (relative to the table's folder), ``cardiac_phase`` in [0, 1),
    ``resp_amplitude`` in [0, 1], ``time_s`` >= 0; each row needs the two phases or the time.
    CSV lines starting with ``#`` are comments. SceneError naming the table and the row.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"frames table {p}: cannot be read ({getattr(e, 'strerror', None) or e})") from None
    base = p.parent
    if p.suffix.lower() == ".toml":
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise SceneError(f"frames table {p}: malformed TOML: {e}") from None
        extra = [k for k in doc if k != "frame"]
        if extra:
            raise SceneError(f"frames table {p}: unknown key {extra[0]!r}; the table holds only [[frame]] entries")
        entries = doc.get("frame", [])
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise SceneError(f"frames table {p}: 'frame' must be an array of tables ([[frame]])")
        rows = [_row(e, base, f"frames table {p}, frame {i + 1}") for i, e in enumerate(entries)]
    elif p.suffix.lower() == ".csv":
        lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
        reader = csv.DictReader(lines, skipinitialspace=True)
        if reader.fieldnames is None or "file" not in [f.strip() for f in reader.fieldnames]:
            raise SceneError(f"frames table {p}: the first line must be a header naming the columns "
                             f"(file, cardiac_phase, resp_amplitude and/or time_s)")
        rows = []
        for i, r in enumerate(reader):
            if None in r:
                raise SceneError(f"frames table {p}, row {i + 1}: more values than header columns")
            rows.append(_row({k.strip(): v for k, v in r.items()}, base, f"frames table {p}, row {i + 1}"))
    else:
        raise SceneError(f"frames table {p}: must be a .toml or .csv file")
    if not rows:
        raise SceneError(f"frames table {p}: no frames")
    return rows


# ---------------------------------------------------------------------------------------
# geometry shared by both formats
@dataclass(frozen=True)
class FrameGeometry:
    """Grid of every frame: ``mu[z, y, x]`` with ``shape`` (nz, ny, nx), voxel ``spacing_mm``
    (dx, dy, dz) and the centre ``origin_mm`` (x, y, z) of voxel [0, 0, 0], LPS, increasing
    coordinates along each array axis."""

    shape: tuple
    spacing_mm: tuple
    origin_mm: tuple

    def axis(self, k: int) -> np.ndarray:
        """Voxel-centre coordinates (mm) along world axis k (0 = x, 1 = y, 2 = z)."""
        n = self.shape[2 - k]
        return self.origin_mm[k] + self.spacing_mm[k] * np.arange(n, dtype=np.float64)

    @property
    def bytes_per_frame(self) -> int:
        return 4 * int(np.prod(self.shape))


def nifti_orientation(affine, shape):
    """How a NIfTI array maps onto ``mu[z, y, x]`` (LPS, increasing): (perm, flips, spacing, origin).

    ``perm[w]`` is the array axis along world axis w (x, y, z); ``flips[w]`` whether that axis
    runs towards decreasing LPS coordinate; ``spacing`` (dx, dy, dz) mm; ``origin`` the LPS
    centre of the first voxel after flipping. Raises ValueError for an oblique affine.
    """
    A = np.diag([-1.0, -1.0, 1.0, 1.0]) @ np.asarray(affine, np.float64)      # RAS -> LPS
    M = A[:3, :3]
    perm, flips, spacing = [0, 0, 0], [False] * 3, [0.0] * 3
    used = set()
    for i in range(3):
        col = M[:, i]
        w = int(np.argmax(np.abs(col)))
        if w in used or not np.abs(col[w]) > 0 or np.any(np.abs(np.delete(col, w)) > 1e-6 * np.abs(col[w])):
            raise ValueError(f"the affine {np.round(np.asarray(affine)[:3, :3], 6).tolist()} is oblique or "
                             f"degenerate; only axis-aligned volumes are read (resample first)")
        used.add(w)
        perm[w], flips[w], spacing[w] = i, bool(col[w] < 0), float(abs(col[w]))
    first = np.zeros(4)
    first[3] = 1.0
    for w in range(3):
        if flips[w]:
            first[perm[w]] = shape[perm[w]] - 1
    origin = A @ first
    return tuple(perm), tuple(flips), tuple(spacing), tuple(float(x) for x in origin[:3])


# ---------------------------------------------------------------------------------------
# frame series
@dataclass(frozen=True)
class FrameSeries:
    """The frames of a voxel phantom: files, grid and per-frame time and state (where known).

    ``times_s`` (K,) or None; ``cardiac``, ``resp`` (K,) or None (timing decides later);
    ``mu_water_per_mm`` from the log (XCAT) or None (NIfTI); ``header`` the log or table file.
    """

    format: str
    header: Path
    files: tuple
    geometry: FrameGeometry
    times_s: np.ndarray | None
    cardiac: np.ndarray | None
    resp: np.ndarray | None
    mu_water_per_mm: float | None
    xcat: XcatLog | None = None
    load_spec: tuple = ()

    @property
    def n_frames(self) -> int:
        return len(self.files)

    def fingerprint(self) -> str:
        """A content hash of the header file and of every frame file (its size and its first and
        last 64 KiB): part of the projection store's key, without reading whole frames."""
        stats = tuple((str(f), st.st_mtime_ns, st.st_size) for f in self.files for st in [f.stat()])
        key = (str(self.header), self.header.stat().st_mtime_ns, stats)
        if key not in _FINGERPRINTS:
            _FINGERPRINTS[key] = self._fingerprint()
        return _FINGERPRINTS[key]

    def _fingerprint(self) -> str:
        h = hashlib.sha256(self.header.read_bytes())
        for f in self.files:
            size = f.stat().st_size
            h.update(f"{f.name}:{size}".encode())
            with open(f, "rb") as fh:
                h.update(fh.read(1 << 16))
                if size > 1 << 17:
                    fh.seek(-(1 << 16), 2)
                    h.update(fh.read(1 << 16))
        return h.hexdigest()[:16]


_FINGERPRINTS: dict = {}


def detect_format(path: Path) -> tuple[str, Path]:
    """(format, header file) of a frames path: an XCAT log, a .toml/.csv table, or a folder holding one."""
    if path.is_dir():
        logs = sorted(p for p in path.iterdir() if p.is_file() and re.search(r"(_log|\.log)$", p.name))
        tables = [path / n for n in ("frames.toml", "frames.csv") if (path / n).is_file()]
        found = [("xcat", p) for p in logs] + [("nifti", p) for p in tables]
        if len(found) != 1:
            what = ", ".join(p.name for _, p in found) or "none"
            raise SceneError(f"phantom.frames = {str(path)!r}: a folder must hold exactly one XCAT log "
                             f"(*_log) or frames table (frames.toml / frames.csv); found {what}")
        return found[0]
    if not path.is_file():
        raise SceneError(f"phantom.frames = {str(path)!r}: no such file or folder")
    if path.suffix.lower() in (".toml", ".csv"):
        return "nifti", path
    return "xcat", path


def _xcat_series(log: XcatLog, byte_order: str, slice_direction: str, centre_mm) -> FrameSeries:
    n, nz = log.array_size, log.n_slices
    expect = 4 * n * n * nz
    if log.n_frames is not None:
        files = [log.frame_path(k) for k in range(1, log.n_frames + 1)]
        for k, f in enumerate(files, 1):
            if not f.is_file():
                raise SceneError(f"XCAT log {log.path}: frame {k} of {log.n_frames} ({f.name}) is missing")
    else:
        files = []
        while log.frame_path(len(files) + 1).is_file():
            files.append(log.frame_path(len(files) + 1))
        if not files:
            raise SceneError(f"XCAT log {log.path}: no frame file {log.frame_path(1).name} beside it")
    for f in files:
        size = f.stat().st_size
        if size != expect:
            raise SceneError(f"XCAT frame {f}: {size} bytes, but the log's {nz} slices x {n} x {n} float32 "
                             f"make {expect}; check array_size and the slice range")
    spacing = (log.pixel_width_mm, log.pixel_width_mm, log.slice_width_mm)
    c = np.asarray(centre_mm, np.float64)
    origin = tuple(float(c[k] - 0.5 * (sh - 1) * spacing[k]) for k, sh in enumerate((n, n, nz)))
    geom = FrameGeometry(shape=(nz, n, n), spacing_mm=spacing, origin_mm=origin)
    dt = log.time_per_frame_s
    times = None if dt is None else dt * np.arange(len(files), dtype=np.float64)
    return FrameSeries(format="xcat", header=log.path, files=tuple(files), geometry=geom, times_s=times,
                       cardiac=None, resp=None, mu_water_per_mm=log.mu_water_per_mm, xcat=log,
                       load_spec=("xcat", "<f4" if byte_order == "little" else ">f4", slice_direction == "inferior",
                                  log.pixel_width_mm, log.mu_water_per_pixel))


def _nibabel():
    try:
        import nibabel
    except ImportError:
        raise SceneError("NIfTI frames need nibabel: pip install 'clrecon[export]'") from None
    return nibabel


def _nifti_series(table: Path, values: str, mu_water: float) -> FrameSeries:
    nib = _nibabel()
    rows = parse_frame_table(table)
    geom = None
    ref = None
    for i, r in enumerate(rows):
        if not r.file.is_file():
            raise SceneError(f"frames table {table}, frame {i + 1}: {r.file} does not exist")
        try:
            img = nib.load(str(r.file))
        except Exception as e:  # noqa: BLE001 - nibabel raises many types for a bad file
            raise SceneError(f"NIfTI frame {r.file}: not a readable NIfTI file ({e})") from None
        shape = tuple(int(s) for s in img.shape)
        if len(shape) == 4 and shape[3] == 1:
            shape = shape[:3]
        if len(shape) != 3:
            raise SceneError(f"NIfTI frame {r.file}: shape {img.shape}; each frame must be one 3D volume")
        try:
            perm, flips, spacing, origin = nifti_orientation(img.affine, shape)
        except ValueError as e:
            raise SceneError(f"NIfTI frame {r.file}: {e}") from None
        g = FrameGeometry(shape=tuple(shape[perm[w]] for w in (2, 1, 0)), spacing_mm=spacing, origin_mm=origin)
        if geom is None:
            geom, ref = g, (perm, flips, r.file)
            continue
        if g.shape != geom.shape or (perm, flips) != ref[:2]:
            raise SceneError(f"NIfTI frame {r.file}: shape {g.shape} [z, y, x] (axes {perm}) differs from the first "
                             f"frame's {geom.shape} (axes {ref[0]}, {ref[2].name})")
        if not np.allclose(g.spacing_mm, geom.spacing_mm, rtol=1e-5, atol=1e-5):
            raise SceneError(f"NIfTI frame {r.file}: voxel spacing {g.spacing_mm} mm differs from the first frame's "
                             f"{geom.spacing_mm} mm ({ref[2].name})")
        if not np.allclose(g.origin_mm, geom.origin_mm, rtol=0, atol=1e-3):
            raise SceneError(f"NIfTI frame {r.file}: origin {g.origin_mm} mm differs from the first frame's "
                             f"{geom.origin_mm} mm ({ref[2].name})")
    times = [r.time_s for r in rows]
    cs = [r.cardiac_phase for r in rows]
    have_t = all(t is not None for t in times)
    have_s = all(c is not None for c in cs)
    return FrameSeries(format="nifti", header=table, files=tuple(r.file for r in rows), geometry=geom,
                       times_s=np.array(times, np.float64) if have_t else None,
                       cardiac=np.array(cs, np.float64) if have_s else None,
                       resp=np.array([r.resp_amplitude for r in rows], np.float64) if have_s else None,
                       mu_water_per_mm=None,
                       load_spec=("nifti", ref[0], ref[1], values, float(mu_water)))


def open_series(frames: str, fmt: str = "auto", *, byte_order: str = "little", slice_direction: str = "superior",
                centre_mm=(0.0, 0.0, 0.0), values: str = "hu", mu_water_per_mm: float = 0.0) -> FrameSeries:
    """The frame series at ``frames`` (header read, every file checked for presence and size; no
    frame data read). ``mu_water_per_mm`` = 0 for NIfTI in HU uses 0.0193 /mm."""
    path = Path(frames)
    found, header = detect_format(path)
    if fmt != "auto" and fmt != found:
        if path.is_dir():
            raise SceneError(f"phantom.format = {fmt!r}, but {path} holds {found} frames ({header.name})")
        found = fmt
    st = header.stat()
    return _open_cached(str(header.resolve()), st.st_mtime_ns, st.st_size, found, byte_order, slice_direction,
                        tuple(float(x) for x in centre_mm), values, float(mu_water_per_mm or MU_WATER_PER_MM))


_SERIES_CACHE: OrderedDict = OrderedDict()


def _open_cached(header, mtime, size, fmt, byte_order, slice_direction, centre, values, mu_water):
    key = (header, mtime, size, fmt, byte_order, slice_direction, centre, values, mu_water)
    if key in _SERIES_CACHE:
        _SERIES_CACHE.move_to_end(key)
        return _SERIES_CACHE[key]
    if fmt == "xcat":
        s = _xcat_series(parse_xcat_log(header), byte_order, slice_direction, centre)
    else:
        s = _nifti_series(Path(header), values, mu_water)
    _SERIES_CACHE[key] = s
    while len(_SERIES_CACHE) > 16:
        _SERIES_CACHE.popitem(last=False)
    return s


# ---------------------------------------------------------------------------------------
# frame data
_FRAMES: OrderedDict = OrderedDict()


def clear_frame_cache() -> None:
    """Drop the frames held in memory (tests; a caller that rewrote frame files in place)."""
    _FRAMES.clear()


def _first_bad(a) -> tuple:
    return tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])


def _plausible(raw, water) -> bool:
    v = np.abs(raw[np.isfinite(raw)])
    nz = v[v > 0]
    return bool(np.all(np.isfinite(raw)) and (nz.size == 0 or (nz.max() <= MAX_MU_OVER_WATER * water
                                                                and nz.min() >= 1e-6 * water)))


def _load_xcat(f: Path, spec, geom: FrameGeometry) -> np.ndarray:
    _, dtype, flip_z, pixel_mm, water_px = spec
    raw = np.memmap(f, dtype=dtype, mode="r", shape=geom.shape)
    sample = np.asarray(raw[:: max(1, geom.shape[0] // 8)])
    if not _plausible(sample, water_px):
        swapped = sample.view(sample.dtype.newbyteorder())          # the same bytes, the other order
        if _plausible(swapped, water_px):
            other = "big" if dtype.startswith("<") else "little"
            raise SceneError(f"XCAT frame {f}: its values are implausible as {'little' if other == 'big' else 'big'}"
                             f"-endian float32 but plausible as {other}-endian: set phantom.byte_order = {other!r}")
    mu = np.array(raw[::-1] if flip_z else raw, dtype=np.float32, order="C")
    del raw
    if not np.all(np.isfinite(mu)):
        idx = _first_bad(mu)
        raise SceneError(f"XCAT frame {f}: non-finite voxel {float(mu[idx])} at [z, y, x] = {list(idx)}")
    bad = np.abs(mu) > MAX_MU_OVER_WATER * water_px
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise SceneError(f"XCAT frame {f}: voxel {mu[idx]:.3g} /pixel at [z, y, x] = {list(idx)} is beyond "
                         f"{MAX_MU_OVER_WATER:g} x water; wrong byte order or not an attenuation frame?")
    mu /= np.float32(pixel_mm)
    return mu


def _load_nifti(f: Path, spec) -> np.ndarray:
    _, perm, flips, values, mu_water = spec
    nib = _nibabel()
    img = nib.load(str(f))
    data = np.asanyarray(img.dataobj)
    if data.ndim == 4:
        data = data[..., 0]
    vol = np.transpose(data, (perm[2], perm[1], perm[0]))         # -> [z, y, x]
    for w, ax in ((0, 2), (1, 1), (2, 0)):
        if flips[w]:
            vol = np.flip(vol, axis=ax)
    vol = np.array(vol, dtype=np.float64)
    if not np.all(np.isfinite(vol)):
        idx = _first_bad(vol)
        raise SceneError(f"NIfTI frame {f}: non-finite voxel {float(vol[idx])} at [z, y, x] = {list(idx)} "
                         f"(LPS order)")
    mu = mu_water * (1.0 + vol / 1000.0) if values == "hu" else vol
    return np.ascontiguousarray(np.maximum(mu, 0.0), dtype=np.float32)


def load_frame(series: FrameSeries, k: int) -> np.ndarray:
    """Frame ``k`` (0-based) as mu (nz, ny, nx) float32 (1/mm), LPS with increasing coordinates.

    Held in a process-wide cache of :data:`FRAME_CACHE_SIZE` frames (least recently used
    dropped). SceneError naming the file for a non-finite voxel or a wrong byte order.
    """
    f = series.files[k]
    st = f.stat()
    key = (str(f), st.st_mtime_ns, st.st_size, series.load_spec)
    if key in _FRAMES:
        _FRAMES.move_to_end(key)
        return _FRAMES[key]
    while len(_FRAMES) >= FRAME_CACHE_SIZE:
        _FRAMES.popitem(last=False)
    if series.format == "xcat":
        mu = _load_xcat(f, series.load_spec, series.geometry)
    else:
        mu = _load_nifti(f, series.load_spec)
    if mu.shape != series.geometry.shape:
        raise SceneError(f"frame {f}: shape {mu.shape} differs from the series' {series.geometry.shape}")
    mu.setflags(write=False)
    _FRAMES[key] = mu
    return mu

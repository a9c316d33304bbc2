"""Standard 3D Gaussian Splatting PLY files, written and read in one vectorised step.

The vertex layout is exactly what nerfstudio 1.1.5's ``ns-export gaussian-splat`` writes in its
default ``sh_coeffs`` colour mode (``ExportGaussianSplat`` in nerfstudio/scripts/exporter.py), so
files open in every 3DGS viewer that reads nerfstudio or INRIA exports:

    x y z nx ny nz f_dc_0..2 [f_rest_0..f_rest_{3K-1}] opacity scale_0..2 rot_0..3

all ``float`` (float32), binary little endian, where
  * nx, ny, nz are zeros,
  * f_rest is channel-major (all R coefficients, then G, then B): nerfstudio stores
    features_rest as [N, K, 3] and transposes it to [N, 3, K] before flattening, to match INRIA,
  * opacity is the logit, scale_* the log scales, rot_* the raw (not normalised) w,x,y,z quaternion.

nerfstudio's writer loops over vertices in Python (minutes for a million Gaussians); here the
vertex rows are one float32 array viewed as a structured array and written with one call per chunk of
rows (:data:`PLY_CHUNK_ROWS`): a file of any size is written with memory for one chunk, and a subset
(an instance) from :class:`GaussianRows` without building the whole table.

Which Gaussians are written follows nerfstudio: any vertex with a non-finite value is dropped, and
so is any vertex whose opacity logit is below -5.5373 (= logit(1/255); the rasteriser skips them).
One deliberate difference: nerfstudio tests finiteness of the 1-D x/y/z/nx/ny/nz columns with
``.all(axis=-1)``, which collapses to a single flag and drops *every* vertex when one position is
NaN; we drop only the offending vertices.

Only numpy is needed here (no nerfstudio import).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, Optional, Sequence, Tuple, Union

import numpy as np

PathLike = Union[str, os.PathLike]

# nerfstudio's threshold, copied literally so both exporters keep exactly the same Gaussians.
MIN_OPACITY_LOGIT = -5.5373
SH_C0 = 0.28209479177387814
# Rows gathered, checked and written at a time: 64k rows of SH degree 3 are 16 MB.
PLY_CHUNK_ROWS = 1 << 16

_PLY_TO_NUMPY = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_NUMPY_TO_PLY = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}


TEMP_MARKER = ".tmp-"
"""In the name of every temporary file or folder made here (next to its target), so stale ones can be found."""


def temp_sibling(path: PathLike, tag: str = "") -> Path:
    """A fresh hidden name next to ``path`` (``.<name><tag>.tmp-<pid>-<random>``); nothing is created."""
    path = Path(path)
    return path.parent / f".{path.name}{tag}{TEMP_MARKER}{os.getpid()}-{secrets.token_hex(6)}"


LEFTOVER_AGE_S = 600.0
"""A hidden temporary sibling older than this is the leftover of a killed process (a write in progress is younger)."""


def sweep_leftovers(path: PathLike, max_age_s: float = LEFTOVER_AGE_S) -> None:
    """Delete the hidden folders and files that writes of ``path`` left beside it when killed (``.<name>.partial``
    or ``.old`` siblings, :func:`temp_sibling`), once they are older than ``max_age_s``, so that a write in progress
    in another process is left alone."""
    path = Path(path)
    now = time.time()
    for leftover in path.parent.glob(f".{glob.escape(path.name)}.*{TEMP_MARKER}*"):
        with contextlib.suppress(OSError):
            if now - leftover.lstat().st_mtime > max_age_s:
                shutil.rmtree(leftover) if leftover.is_dir() and not leftover.is_symlink() else leftover.unlink()


def make_temp_dir(path: PathLike, tag: str = "") -> Path:
    """Create an empty folder with a fresh name next to ``path`` (to be renamed onto it later).

    Made with mode 0o777 less the umask, as any folder the user creates; tempfile.mkdtemp would
    make it 0700 and the renamed export unreadable to others.
    """
    while True:
        candidate = temp_sibling(path, tag)
        try:
            candidate.mkdir(0o777)
            return candidate
        except FileExistsError:  # pragma: no cover - 48 random bits
            continue


def replace_folder(staging: PathLike, target: PathLike) -> None:
    """Rename the finished folder ``staging`` onto ``target``, replacing a folder there (moved aside first, then
    deleted), so that a reader finds the old folder or the new one, never a mix."""
    staging, target = Path(staging), Path(target)
    if target.exists():
        old = temp_sibling(target, ".old")
        target.rename(old)
        staging.rename(target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        staging.rename(target)


@contextlib.contextmanager
def atomic_write(path: PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file next to ``path``; on success it replaces ``path`` in one rename.

    Readers never see a half-written file, and a crash leaves the previous file (if any) intact.
    The file gets mode 0o666 less the umask, as ``open`` gives (tempfile.mkstemp would make it 0600).
    """
    path = Path(path)
    tmp_name = temp_sibling(path)
    fd = os.open(tmp_name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        try:
            with os.fdopen(fd, mode) as handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
        except OSError as error:
            named = write_error_naming(error, path)
            if named is error:
                raise
            raise named from error
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def write_error_naming(error: OSError, path: PathLike) -> OSError:
    """``error``, raised while writing ``path``, as an ``OSError`` that names ``path`` and its errno.

    A failed ``write()`` names no file, and numpy's short write (``np.save`` onto a full disk: "32768
    requested and 6080 written") has no errno either; such an error gets ``path`` and, for a short
    write, ENOSPC when the disk has less room left than was asked for (EIO otherwise). An error that
    already names a file is returned as it is.
    """
    if error.filename is not None:
        return error
    code = error.errno
    if code is None:
        short = re.search(r"(\d+) requested and (\d+) written", str(error))
        if short is None:
            return error
        code = errno.EIO
        with contextlib.suppress(OSError):
            stats = os.statvfs(Path(path).parent)
            if stats.f_bavail * stats.f_frsize < int(short.group(1)) - int(short.group(2)):
                code = errno.ENOSPC
    return OSError(code, os.strerror(code), os.fspath(path))


def jsonable(value: Any) -> Any:
    """``value`` with what ``json.dumps`` refuses made plain: numpy scalars and arrays, paths, non-string keys."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return value


def gaussian_property_names(num_rest_coeffs: int) -> list:
    """Vertex property names in file order; ``num_rest_coeffs`` is K of features_rest [N, K, 3]."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * num_rest_coeffs)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def _as_numpy(array) -> np.ndarray:
    if hasattr(array, "detach"):  # torch tensor, without importing torch here
        array = array.detach().cpu().numpy()
    return np.asarray(array)


def gaussian_vertex_table(
    means,
    features_dc,
    features_rest,
    opacity_logits,
    log_scales,
    quats,
) -> np.ndarray:
    """All vertex properties as one float32 array [N, P] in the order of ``gaussian_property_names``.

    features_dc [N, 3] (or [N, 1, 3]) are SH DC coefficients; features_rest [N, K, 3] (K may be 0, or None for
    degree 0); opacity_logits [N] or [N, 1]; log_scales [N, 3]; quats [N, 4] as w, x, y, z.
    """
    means = _as_numpy(means)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape [N, 3], got {list(means.shape)}")
    n = means.shape[0]
    features_dc = _as_numpy(features_dc)
    if features_dc.ndim == 3 and features_dc.shape[1] == 1:  # [N, 1, 3] as in SH-stacked colours
        features_dc = features_dc[:, 0]
    if features_dc.shape != (n, 3):
        raise ValueError(f"features_dc must have shape [N, 3] (N={n}), got {list(features_dc.shape)}")
    if features_rest is None:
        features_rest = np.zeros((n, 0, 3), dtype=np.float32)
    features_rest = _as_numpy(features_rest)
    if features_rest.ndim != 3 or features_rest.shape[0] != n or features_rest.shape[2] != 3:
        raise ValueError(f"features_rest must have shape [N, K, 3] (N={n}), got {list(features_rest.shape)}")
    opacity_logits = _as_numpy(opacity_logits).reshape(-1)
    log_scales = _as_numpy(log_scales)
    quats = _as_numpy(quats)
    for name, value, shape in (
        ("opacity_logits", opacity_logits, (n,)),
        ("log_scales", log_scales, (n, 3)),
        ("quats", quats, (n, 4)),
    ):
        if value.shape != shape:
            raise ValueError(f"{name} must have shape {list(shape)} to match means, got {list(value.shape)}")

    k = features_rest.shape[1]
    table = np.empty((n, 9 + 3 * k + 8), dtype=np.float32)
    table[:, 0:3] = means
    table[:, 3:6] = 0.0
    table[:, 6:9] = features_dc
    # [N, K, 3] -> [N, 3, K]: INRIA's channel-major order, as nerfstudio's transpose(1, 2)
    table[:, 9 : 9 + 3 * k] = features_rest.transpose(0, 2, 1).reshape(n, 3 * k)
    o = 9 + 3 * k
    table[:, o] = opacity_logits
    table[:, o + 1 : o + 4] = log_scales
    table[:, o + 4 : o + 8] = quats
    return table


class GaussianRows:
    """Rows of the vertex table of Gaussians (``gaussian_vertex_table``'s arguments), made on demand for the rows
    asked for: ``write_gaussian_table`` writes a subset without the whole table in memory."""

    def __init__(self, means, features_dc, features_rest, opacity_logits, log_scales, quats):
        means = _as_numpy(means)
        rest = None if features_rest is None else _as_numpy(features_rest)
        dc, opacities, scales, rotations = (_as_numpy(a) for a in (features_dc, opacity_logits, log_scales, quats))
        self.arrays = (means, dc, rest, opacities, scales, rotations)
        self.shape = (int(means.shape[0]), 17 + 3 * (0 if rest is None else int(rest.shape[1])))

    def rows(self, indices: Union[np.ndarray, slice]) -> np.ndarray:
        """float32 [len(indices), P]: the table's rows ``indices`` (integer indices or a slice)."""
        return gaussian_vertex_table(*(None if a is None else a[indices] for a in self.arrays))


VertexRows = Union[np.ndarray, GaussianRows]


def exportable_mask(table: np.ndarray) -> np.ndarray:
    """Rows nerfstudio's exporter keeps: every value finite and opacity logit >= logit(1/255)."""
    opacity_column = table.shape[1] - 8
    keep = np.isfinite(table).all(axis=1)
    keep &= ~(table[:, opacity_column] < MIN_OPACITY_LOGIT)
    return keep


def _header(names: Sequence[str], types: Sequence[str], count: int, comments: Sequence[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {count}")
    lines += [f"property {t} {n}" for n, t in zip(names, types)]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_vertex_ply(path: PathLike, columns: Dict[str, np.ndarray], comments: Sequence[str] = ()) -> int:
    """Write a PLY with one vertex element whose properties are ``columns`` (in dict order), atomically.

    Each column is 1-D of the same length; its numpy dtype picks the PLY type (float32 -> float,
    int32 -> int, uint8 -> uchar, ...). Returns the vertex count.
    """
    if not columns:
        raise ValueError("write_vertex_ply needs at least one column")
    arrays = {name: np.ascontiguousarray(np.asarray(col).reshape(-1)) for name, col in columns.items()}
    counts = {a.shape[0] for a in arrays.values()}
    if len(counts) != 1:
        raise ValueError(f"all PLY columns must have the same length, got {sorted(counts)}")
    count = counts.pop()
    dtype = []
    for name, array in arrays.items():
        code = array.dtype.str.lstrip("<>|=")
        if code not in _NUMPY_TO_PLY:
            raise ValueError(f"column {name!r} has dtype {array.dtype}; use float32/float64/int8-32/uint8-32")
        dtype.append((name, "<" + code if code[1] != "1" else code))
    record = np.empty(count, dtype=np.dtype(dtype))
    for name, array in arrays.items():
        record[name] = array
    header = _header(list(arrays), [_NUMPY_TO_PLY[np.dtype(t).str.lstrip("<>|=")] for _, t in dtype], count, comments)
    with atomic_write(path) as handle:
        handle.write(header)
        handle.write(record.tobytes())
    return count


def write_gaussian_table(
    path: PathLike,
    table: VertexRows,
    select: Optional[np.ndarray] = None,
    filter_invalid: bool = True,
    comments: Sequence[str] = ("Generated by votesplat_ns", "Vertical Axis: z"),
    chunk_rows: int = PLY_CHUNK_ROWS,
) -> np.ndarray:
    """Write rows of a ``gaussian_vertex_table`` (or of :class:`GaussianRows`) as a standard 3DGS PLY, atomically.

    Build the table (or rows) once and call this per subset (instances, background, ...). ``select``
    ([N] bool or integer indices) picks the rows to consider; with ``filter_invalid`` the
    non-finite and too-transparent ones are then dropped as nerfstudio does. Returns the indices
    (into the table) of the written vertices, in file order, so per-vertex side files (instance
    ids) can be aligned with the PLY. Rows are gathered ``chunk_rows`` at a time (twice with
    ``filter_invalid``: the header counts the kept ones), so memory does not grow with the file.
    """
    if isinstance(table, np.ndarray):
        if table.ndim != 2 or table.dtype != np.float32 or (table.shape[1] - 17) % 3:
            raise ValueError("table must be a float32 [N, 17 + 3K] array from gaussian_vertex_table")
        array = table
        rows_of: Callable[[Any], np.ndarray] = lambda index: array[index]  # noqa: E731
    else:
        rows_of = table.rows
    num_rows, width = table.shape
    if select is None:
        indices = np.arange(num_rows)
    else:
        select = np.asarray(select)
        indices = np.flatnonzero(select) if select.dtype == bool else select.astype(np.int64).reshape(-1)
    chunk_rows = max(1, int(chunk_rows))
    starts = range(0, indices.size, chunk_rows)
    if filter_invalid:
        kept = [part[exportable_mask(rows_of(part))] for part in (indices[a : a + chunk_rows] for a in starts)]
        indices = np.concatenate(kept) if kept else indices
    names = gaussian_property_names((width - 17) // 3)
    record_dtype = np.dtype([(name, "<f4") for name in names])
    header = _header(names, ["float"] * len(names), int(indices.size), comments)
    with atomic_write(path) as handle:
        handle.write(header)
        for start in range(0, indices.size, chunk_rows):
            rows = np.ascontiguousarray(rows_of(indices[start : start + chunk_rows]), dtype=np.float32)
            handle.write(rows.view(record_dtype).data)
    return indices


def read_ply_header(path: PathLike):
    """Parse a PLY header: returns (format, vertex_count, [(name, numpy dtype str)], comments, data offset)."""
    with open(path, "rb") as handle:
        if handle.readline().strip() != b"ply":
            raise ValueError(f"{path} is not a PLY file (missing 'ply' magic line)")
        fmt, count, props, comments, element = None, None, [], [], None
        while True:
            line = handle.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no end_header line")
            words = line.decode("ascii", errors="replace").split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "comment":
                comments.append(line.decode("ascii", errors="replace")[len("comment ") :].rstrip("\r\n"))
            elif words[0] == "element":
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
                elif int(words[2]) != 0:
                    raise ValueError(f"{path}: only vertex-only PLY files are supported, found element {element!r}")
            elif words[0] == "property" and element == "vertex":
                if words[1] == "list":
                    raise ValueError(f"{path}: list properties are not supported in Gaussian PLY files")
                if words[1] not in _PLY_TO_NUMPY:
                    raise ValueError(f"{path}: unknown PLY property type {words[1]!r}")
                props.append((words[2], _PLY_TO_NUMPY[words[1]]))
        offset = handle.tell()
    if fmt not in PLY_FORMATS:
        raise ValueError(f"{path}: PLY format {fmt!r} is not supported, only {', '.join(PLY_FORMATS)}")
    if count is None:
        raise ValueError(f"{path}: PLY header declares no vertex element")
    return fmt, count, props, comments, offset


PLY_FORMATS = ("binary_little_endian", "binary_big_endian", "ascii")


def _vertex_dtype(fmt: str, props) -> np.dtype:
    order = ">" if fmt == "binary_big_endian" else "<"
    return np.dtype([(name, order + code if code[1] != "1" else code) for name, code in props])


def read_vertex_data(path: PathLike, fmt: str, count: int, props, offset: int) -> np.ndarray:
    """The vertex records after a PLY header (:func:`read_ply_header`'s values) as a structured array; fewer than
    ``count`` when the file is truncated. An ASCII value that is not a number raises ``ValueError``."""
    dtype = _vertex_dtype(fmt, props)
    if fmt != "ascii":
        return np.fromfile(path, dtype=dtype, count=count, offset=offset)
    with open(path, "rb") as handle:
        handle.seek(offset)
        values = np.loadtxt(handle, dtype=np.float64, max_rows=count, ndmin=2) if count else np.zeros((0, len(props)))
    if values.shape[0] and values.shape[1] != len(props):
        raise ValueError(f"its vertex lines hold {values.shape[1]} values, the header declares {len(props)} properties")
    data = np.empty(values.shape[0], dtype=dtype)
    for column, (name, _) in enumerate(props):
        data[name] = values[:, column]
    return data


def read_vertex_ply(path: PathLike) -> Dict[str, np.ndarray]:
    """Every vertex property of a PLY (binary or ASCII) as a dict of 1-D arrays (file order)."""
    fmt, count, props, _, offset = read_ply_header(path)
    data = read_vertex_data(path, fmt, count, props, offset)
    if data.shape[0] != count:
        raise ValueError(f"{path}: file is truncated ({data.shape[0]} of {count} vertices)")
    return {name: data[name].copy() for name, _ in props}


_REQUIRED_GAUSSIAN_PROPERTIES = (
    ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_OPTIONAL_GAUSSIAN_PROPERTIES = ("nx", "ny", "nz")  # zeros in every writer; gsplat's export_splats leaves them out
VOTESPLAT_OFFSET_PROPERTIES = ("vote_offset_0", "vote_offset_1", "vote_offset_2")
"""Columns the official VoteSplat code adds to its 3DGS PLY (each Gaussian's vote offset): accepted and not read,
as they do not change what the scene looks like (a retrofit learns its own offsets; ``ns/retrofit_source.py`` says so)."""
MAX_SH_DEGREE = 4  # the highest degree gsplat renders


class GaussianPlyError(ValueError):
    """A file that is not a usable standard 3DGS PLY; the message names the file and says what is wrong."""


def sh_degree_of_rest_count(num_rest: int) -> Optional[int]:
    """The SH degree d with 3 * ((d + 1)^2 - 1) == ``num_rest`` f_rest_* properties, or None if there is none."""
    for degree in range(MAX_SH_DEGREE + 1):
        if 3 * ((degree + 1) ** 2 - 1) == num_rest:
            return degree
    return None


def _gaussians_from_columns(columns: Dict[str, np.ndarray], num_rest: int) -> Dict[str, np.ndarray]:
    n = columns["x"].shape[0]

    def stack(names):
        if not names:
            return np.zeros((n, 0), np.float32)
        return np.stack([columns[k].astype(np.float32) for k in names], axis=1)

    # channel-major in the file (all R coefficients, then G, then B), [N, K, 3] in splatfacto
    rest = stack([f"f_rest_{i}" for i in range(num_rest)]).reshape(n, 3, num_rest // 3).transpose(0, 2, 1)
    return {
        "means": stack(["x", "y", "z"]),
        "features_dc": stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "features_rest": np.ascontiguousarray(rest),
        "opacity_logits": columns["opacity"].astype(np.float32),
        "log_scales": stack([f"scale_{i}" for i in range(3)]),
        "quats": stack([f"rot_{i}" for i in range(4)]),
    }


def read_gaussian_ply(path: PathLike) -> Dict[str, np.ndarray]:
    """Read a standard 3DGS PLY back into arrays shaped like splatfacto's parameters.

    Returns means [N,3], features_dc [N,3], features_rest [N,K,3] (back in nerfstudio's
    coefficient-major order), opacity_logits [N], log_scales [N,3], quats [N,4] (all float32).
    Lenient: other properties are ignored. :func:`read_3dgs_ply` checks a file from elsewhere.
    """
    columns = read_vertex_ply(path)
    missing = [name for name in _REQUIRED_GAUSSIAN_PROPERTIES if name not in columns]
    if missing:
        raise ValueError(f"{path} is not a 3D Gaussian Splatting PLY: missing properties {missing}")
    num_rest = sum(1 for name in columns if name.startswith("f_rest_"))
    if num_rest % 3:
        raise ValueError(f"{path}: {num_rest} f_rest_* properties is not a multiple of 3")
    return _gaussians_from_columns(columns, num_rest)


def _names_list(names: Sequence[str], limit: int = 6) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _column_selector(columns: Sequence[int]) -> Union[slice, np.ndarray]:
    """What picks ``columns`` of a [rows, P] block: a slice (a view) when they are consecutive, as in every
    writer's layout, else their indices (numpy's fancy indexing, a copy several times slower)."""
    first = columns[0]
    if list(columns) == list(range(first, first + len(columns))):
        return slice(first, first + len(columns))
    return np.asarray(columns, dtype=np.intp)


def _read_float32_gaussians(
    path: PathLike, names: Sequence[str], count: int, offset: int, num_rest: int, chunk_rows: int = PLY_CHUNK_ROWS
) -> Optional[Dict[str, np.ndarray]]:
    """:func:`read_3dgs_ply`'s arrays from a binary PLY whose ``names`` (its properties, in file order, checked)
    are all float32 in this machine's byte order: ``chunk_rows`` rows at a time are read into one buffer,
    checked to be finite (all but the vote offsets) and copied into the arrays, so memory holds the arrays and
    one chunk, never a table of the whole file. None when a value is not finite or the file ends early."""
    width = len(names)
    column = {name: index for index, name in enumerate(names)}
    k = num_rest // 3

    def select(group: Sequence[str]) -> Union[slice, np.ndarray]:
        return _column_selector([column[name] for name in group])

    targets = {
        "means": (select(["x", "y", "z"]), (count, 3)),
        "features_dc": (select(["f_dc_0", "f_dc_1", "f_dc_2"]), (count, 3)),
        "opacity_logits": (column["opacity"], (count,)),
        "log_scales": (select([f"scale_{i}" for i in range(3)]), (count, 3)),
        "quats": (select([f"rot_{i}" for i in range(4)]), (count, 4)),
    }
    arrays: Dict[str, np.ndarray] = {key: np.empty(shape, dtype=np.float32) for key, (_, shape) in targets.items()}
    features_rest = np.empty((count, k, 3), dtype=np.float32)
    # channel-major in the file (f_rest_{c K + j} is coefficient j of channel c), [N, K, 3] in splatfacto
    rest = select([f"f_rest_{c * k + j}" for c in range(3) for j in range(k)]) if k else None
    checked = [column[name] for name in names if name not in VOTESPLAT_OFFSET_PROPERTIES]
    check: Union[slice, np.ndarray] = _column_selector(checked)
    chunk_rows = max(1, int(chunk_rows))
    buffer = np.empty((min(chunk_rows, count), width), dtype=np.float32)
    with open(path, "rb") as handle:
        handle.seek(offset)
        for start in range(0, count, chunk_rows):
            block = buffer[: min(chunk_rows, count - start)]
            if handle.readinto(block.data.cast("B")) != block.nbytes:
                return None
            if not np.isfinite(block[:, check]).all():
                return None
            stop = start + block.shape[0]
            for key, (columns, _) in targets.items():
                arrays[key][start:stop] = block[:, columns]
            if rest is not None:
                features_rest[start:stop] = block[:, rest].reshape(-1, 3, k).transpose(0, 2, 1)
    arrays["features_rest"] = features_rest
    return {
        key: arrays[key] for key in ("means", "features_dc", "features_rest", "opacity_logits", "log_scales", "quats")
    }


def read_3dgs_ply(path: PathLike, chunk_rows: int = PLY_CHUNK_ROWS) -> Tuple[Dict[str, np.ndarray], int]:
    """Read and check a standard 3DGS PLY written by any tool; returns (arrays as ``read_gaussian_ply``, SH degree).

    Accepted: binary (little or big endian) or ASCII, one vertex element with exactly the properties x y z
    [nx ny nz] f_dc_0..2 f_rest_0..f_rest_{3((d+1)^2-1)-1} opacity scale_0..2 rot_0..3 in any
    order and any numeric type (the layout of the original 3DGS writer, gsplat's export_splats,
    ``ns-export gaussian-splat`` and :func:`write_gaussian_table`), plus the official VoteSplat code's
    vote_offset_0..2 (:data:`VOTESPLAT_OFFSET_PROPERTIES`, not read). Anything else — not a PLY, a
    truncated file, no vertices, missing or extra properties (an extra one such as Mip-Splatting's
    filter_3D changes what the scene looks like), f_rest for no SH degree, a NaN or infinite
    value — raises :class:`GaussianPlyError` with a one-line message naming the file.

    A binary file whose properties are all float32 (every writer's usual layout) is read ``chunk_rows`` rows at
    a time straight into the arrays (:func:`_read_float32_gaussians`), without a table of the whole file.
    """
    what_to_do = "give a 3DGS PLY (ns-export gaussian-splat, the original 3DGS or gsplat's simple_trainer)"
    try:
        fmt, count, props, _, offset = read_ply_header(path)
    except FileNotFoundError:
        raise GaussianPlyError(f"{path} does not exist; {what_to_do}") from None
    except (ValueError, IndexError, UnicodeError) as err:
        reason = str(err) if str(path) in str(err) else f"{path}: {err}"
        raise GaussianPlyError(f"{reason}; {what_to_do}") from None
    if count < 0:
        raise GaussianPlyError(f"{path}: PLY header declares {count} vertices; {what_to_do}")
    names = [name for name, _ in props]
    duplicated = sorted({name for name in names if names.count(name) > 1})
    if duplicated:
        raise GaussianPlyError(f"{path}: properties {_names_list(duplicated)} appear more than once; {what_to_do}")
    rest_names = [name for name in names if name.startswith("f_rest_")]
    num_rest = len(rest_names)
    expected_rest = [f"f_rest_{i}" for i in range(num_rest)]
    missing = [name for name in _REQUIRED_GAUSSIAN_PROPERTIES if name not in names]
    missing += [name for name in expected_rest if name not in rest_names]
    known = (
        set(_REQUIRED_GAUSSIAN_PROPERTIES)
        | set(_OPTIONAL_GAUSSIAN_PROPERTIES)
        | set(expected_rest)
        | set(VOTESPLAT_OFFSET_PROPERTIES)
    )
    extra = [name for name in names if name not in known]
    if missing:
        hint = (
            "; it stores RGB colours, export with --ply-color-mode sh_coeffs"
            if "red" in names and "f_dc_0" not in names
            else ""
        )
        raise GaussianPlyError(
            f"{path} is not a 3DGS PLY: it lacks the properties {_names_list(missing)}{hint}; {what_to_do}"
        )
    if extra:
        raise GaussianPlyError(
            f"{path} has properties a standard 3DGS PLY does not have ({_names_list(extra)}); they would change the scene "
            f"and are not read: {what_to_do}"
        )
    sh_degree = sh_degree_of_rest_count(num_rest)
    if sh_degree is None:
        raise GaussianPlyError(
            f"{path} has {num_rest} f_rest_* properties, which fits no SH degree (3*((d+1)^2-1): 0, 9, 24, 45, 72); {what_to_do}"
        )
    if count == 0:
        raise GaussianPlyError(f"{path} holds no Gaussians (its vertex count is 0); export the trained scene again")
    dtype = _vertex_dtype(fmt, props)
    size = os.path.getsize(path)
    if fmt != "ascii" and size - offset < count * dtype.itemsize:
        raise GaussianPlyError(
            f"{path} is truncated: its header declares {count} Gaussians ({count * dtype.itemsize} bytes) but only "
            f"{max(size - offset, 0)} bytes follow; copy or export the file again"
        )
    if fmt != "ascii" and all(dtype[name] == np.dtype(np.float32) for name in names):
        arrays = _read_float32_gaussians(path, names, count, offset, num_rest, chunk_rows)
        if arrays is not None:
            return arrays, sh_degree
        # a value that is not finite, or a file cut short since its size was taken: the full read below says which
    try:
        data = read_vertex_data(path, fmt, count, props, offset)
    except ValueError as err:  # an ASCII value that is not a number
        raise GaussianPlyError(f"{path}: its vertex values cannot be read ({err}); {what_to_do}") from None
    if data.shape[0] < count:
        raise GaussianPlyError(
            f"{path} is truncated: its header declares {count} Gaussians but only {data.shape[0]} follow; copy or "
            "export the file again"
        )
    columns = {name: data[name] for name in names}
    bad_names = [
        name for name in names if name not in VOTESPLAT_OFFSET_PROPERTIES and not np.isfinite(columns[name]).all()
    ]
    if bad_names:
        bad_rows = ~np.all([np.isfinite(columns[name]) for name in bad_names], axis=0)
        raise GaussianPlyError(
            f"{path}: {int(bad_rows.sum())} of {count} Gaussians have NaN or infinite values (in {_names_list(bad_names)}); "
            "export the scene again (ns-export gaussian-splat leaves such Gaussians out) or drop them"
        )
    return _gaussians_from_columns(columns, num_rest), sh_degree


def write_instance_id_file(path: PathLike, instance_ids: np.ndarray) -> None:
    """Save per-vertex instance ids (int32, -1 = none) as a .npy beside a PLY, atomically."""
    ids = np.asarray(instance_ids).astype(np.int32).reshape(-1)
    with atomic_write(path) as handle:
        np.save(handle, ids)

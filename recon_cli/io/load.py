"""Load any recon input and save any stage output, in the format the file name says.

The format registry: :data:`FORMATS` maps a format name to its suffixes, what it holds and
the module that reads (and writes) it. A file's format is chosen by its suffix
(case-insensitive; the longest, so ``.copc.laz`` is COPC), a LAS/LAZ name holding a COPC
file being read as COPC; a name without a suffix, and ``-`` (standard input), are read by
content (PLY and grid ``.npz`` as before, and every format with a signature), and written
as PLY (a grid as ``.npz``) unless a format is given. An unknown suffix is an error that
lists the supported ones.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from typing import Any

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.grid import Grid
from recon_cli.io.hint import ReadHint
from recon_cli.io.npz import is_npz, read_grid, write_grid
from recon_cli.io.ply import read_bytes, read_ply, write_ply


@dataclass(frozen=True)
class Format:
    """One file format and what it holds.

    ``holds`` is ``mesh`` (meshes and clouds), ``points`` (clouds only), ``triangles`` (meshes
    only) or ``grid``.
    """

    name: str
    suffixes: tuple[str, ...]
    holds: str
    module: str
    writes: bool
    extra: str | None
    kept: str

    def decoder(self):
        """The format module's ``decode_<module>`` function (imported on first use)."""
        mod = importlib.import_module(f"recon_cli.io.{self.module}")
        return getattr(mod, f"decode_{self.module}")


#: format name -> its suffixes, what it holds and how it is read and written
FORMATS: dict[str, Format] = {
    f.name: f
    for f in (
        Format(
            "ply",
            (".ply",),
            "mesh",
            "ply",
            True,
            None,
            "everything: every element and property, comments, obj_info; float32/float64 as stored",
        ),
        Format(
            "obj",
            (".obj",),
            "mesh",
            "obj",
            True,
            None,
            "v (float64), v colours, vn per vertex, f (polygons fan-triangulated); # history",
        ),
        Format(
            "off",
            (".off",),
            "mesh",
            "off",
            True,
            None,
            "vertices (float64), normals and colours (NOFF/COFF), faces, face colours",
        ),
        Format(
            "stl",
            (".stl",),
            "triangles",
            "stl",
            True,
            None,
            "triangles, corners welded exactly (tolerance 0); binary float32 / ASCII float64; "
            "attribute word",
        ),
        Format(
            "xyz",
            (".xyz", ".txt", ".csv", ".pts", ".xyzn", ".xyzrgb"),
            "points",
            "xyz",
            True,
            None,
            "x y z (float64), normals, colours, every other column as an attribute; header line",
        ),
        Format(
            "pcd",
            (".pcd",),
            "points",
            "pcd",
            True,
            None,
            "every field (x y z float32/float64, normals, rgb/rgba, the rest as attributes); "
            "viewpoint",
        ),
        Format(
            "las",
            (".las", ".laz"),
            "points",
            "las",
            True,
            "las",
            "float64 coordinates (scale/offset kept), colours, every dimension as an "
            "attribute, VLRs",
        ),
        Format(
            "copc",
            (".copc.laz",),
            "points",
            "copc",
            False,
            "las",
            "as LAS/LAZ; a box and octree levels (filter --crop --level --resolution) decode "
            "only the nodes they need",
        ),
        Format(
            "e57",
            (".e57",),
            "points",
            "e57",
            False,
            "e57",
            "all scans in the file frame (float64), intensity, colours (read only)",
        ),
        Format(
            "gltf",
            (".glb", ".gltf"),
            "mesh",
            "gltf",
            True,
            None,
            "positions (float32 + a float64 node translation), normals, COLOR_0, indices, "
            "other attributes as _NAME, history; every triangle primitive of the scene",
        ),
        Format("npz", (".npz",), "grid", "npz", True, None, "SDF grids (recon sdf / mcubes)"),
    )
}
_BY_SUFFIX = {s: f for f in FORMATS.values() for s in f.suffixes}
# suffixes of two parts (".copc.laz"), matched before the last part alone
_LONG_SUFFIXES = sorted((s for s in _BY_SUFFIX if s.count(".") > 1), key=len, reverse=True)


def supported() -> str:
    """The supported suffixes, for messages."""
    return ", ".join(s for f in FORMATS.values() for s in f.suffixes)


def format_choices() -> str:
    """What ``--format`` and its kin take, for their help and messages.

    Every format's name, its other suffixes in brackets (``las (laz)``), and whether recon
    writes it.
    """
    out = []
    for f in FORMATS.values():
        others = [s[1:] for s in f.suffixes if s[1:] != f.name]
        name = f"{f.name} ({', '.join(others)})" if others else f.name
        out.append(name if f.writes else f"{name} [read only]")
    return ", ".join(out)


def format_named(name: str) -> Format:
    """The format called ``name`` (a name or a suffix, any case)."""
    key = name.lower().lstrip(".")
    if key in FORMATS:
        return FORMATS[key]
    if "." + key in _BY_SUFFIX:
        return _BY_SUFFIX["." + key]
    raise ParameterError(f"unknown format {name!r} (formats: {format_choices()})")


def format_of(path: str | os.PathLike, given: str | None = None) -> Format | None:
    """The format of ``path`` by ``given`` or its suffix; None for ``-`` or no suffix."""
    if given:
        return format_named(given)
    p = str(path)
    if p == "-":
        return None
    name = os.path.basename(p).lower()
    for long in _LONG_SUFFIXES:
        if name.endswith(long) and len(name) > len(long):
            return _BY_SUFFIX[long]
    ext = os.path.splitext(p)[1].lower()
    if not ext:
        return None
    if ext not in _BY_SUFFIX:
        raise ParameterError(
            f"{p}: unknown file type {ext!r} (supported: {supported()}; or give --format)"
        )
    return _BY_SUFFIX[ext]


def sniff(data) -> Format:
    """The format of a file's bytes by content (PLY when nothing else is recognised)."""
    from recon_cli.io.stl import is_binary_stl
    from recon_cli.io.text import as_uint8

    buf = as_uint8(data)
    head = bytes(buf[:512])
    start = head.lstrip()
    if head.startswith(b"ply"):
        return FORMATS["ply"]
    if is_npz(head):
        return FORMATS["npz"]
    if head.startswith(b"LASF"):
        return FORMATS["las"]
    if head.startswith(b"ASTM-E57"):
        return FORMATS["e57"]
    if head.startswith(b"glTF") or start.startswith(b"{"):
        return FORMATS["gltf"]
    if start.startswith((b"# .PCD", b"VERSION", b"FIELDS")):
        return FORMATS["pcd"]
    word = start.split(None, 1)[0] if start.strip() else b""
    if word in (b"OFF", b"COFF", b"NOFF", b"CNOFF", b"NCOFF"):
        return FORMATS["off"]
    if is_binary_stl(buf) or (word == b"solid" and b"facet" in head):
        return FORMATS["stl"]
    if word in (b"v", b"vn", b"vt", b"f", b"o", b"g", b"mtllib", b"usemtl") or b"\nv " in head:
        return FORMATS["obj"]
    first = word.replace(b";", b",").split(b",")[0].strip(b"\"'").lower()
    if start[:1].isdigit() or start[:1] in (b"-", b"+", b".") or first in (b"x", b"//x", b"#"):
        return FORMATS["xyz"]
    return FORMATS["ply"]


def load_detailed(
    path: str | os.PathLike, format: str | None = None, hint: ReadHint | None = None
) -> tuple[Any, dict, Format]:
    """Read ``path`` (``-``: stdin): ``(object, details for recon info, format)``.

    ``details`` is empty for PLY and grids (:mod:`recon_cli.info` describes those itself).
    ``hint``: what the stage that reads the file keeps (:class:`~recon_cli.io.hint.ReadHint`);
    a COPC file decodes only that, other files are read whole (octree levels are refused for
    them, before anything is read). A LAS/LAZ name holding a COPC file is read as COPC unless
    ``format`` says LAS.
    """
    where = "<stdin>" if str(path) == "-" else str(path)
    fmt = format_of(path, format)
    if fmt is not None and fmt.name == "las" and format is None and str(path) != "-":
        from recon_cli.io.copc import is_copc_file

        fmt = FORMATS["copc"] if is_copc_file(path) else fmt
    if fmt is not None and str(path) != "-":
        _check_hint(fmt, hint, where)
    if fmt is not None and fmt.name in ("las", "e57", "copc") and str(path) != "-":
        # laspy and pye57 read the file themselves (no second copy of its bytes)
        if not os.path.isfile(path):
            if os.path.isdir(path):
                raise InputError("is a directory, not a file", where)
            raise InputError("no such file", where)
        kw = {"hint": hint} if fmt.name == "copc" else {}
        obj, details = fmt.decoder()(None, where, path=str(path), **kw)
        return obj, details, fmt
    if fmt is not None and fmt.name == "ply" and str(path) != "-" and os.path.isfile(path):
        return read_ply(path), {}, fmt
    if fmt is not None and fmt.name == "npz" and str(path) != "-" and os.path.isfile(path):
        return read_grid(path), {}, fmt  # reads the stored sdf straight into its array
    return decode(read_bytes(path), path, fmt, hint=hint)


def _check_hint(fmt: Format, hint: ReadHint | None, where: str) -> None:
    """Refuse octree levels for a format that has none, before reading anything."""
    if hint is not None and hint.wants_levels and fmt.name != "copc":
        raise ParameterError(
            f"{where}: {hint.asked or 'octree levels'} chooses the octree levels of a COPC file "
            f"(.copc.laz); this is {fmt.name.upper()}"
        )


def decode(
    data, path: str | os.PathLike, fmt: Format | None = None, hint: ReadHint | None = None
) -> tuple[Any, dict, Format]:
    """Decode the bytes of a file named ``path`` in ``fmt`` (None: by content).

    ``hint``: as :func:`load_detailed` takes it (LAS bytes that are COPC are read as COPC).
    """
    if fmt is None:
        fmt = sniff(data)
    where = "<stdin>" if str(path) == "-" else str(path)
    if fmt.name == "las" and hint is not None:
        from recon_cli.io.copc import HEAD_BYTES, is_copc
        from recon_cli.io.text import as_uint8

        fmt = FORMATS["copc"] if is_copc(bytes(as_uint8(data)[:HEAD_BYTES])) else fmt
    _check_hint(fmt, hint, where)
    if fmt.name == "npz":
        return read_grid(path, data), {}, fmt
    if fmt.name == "ply":
        return read_ply(path, data), {}, fmt
    kw = {"hint": hint} if fmt.name == "copc" else {}
    obj, details = fmt.decoder()(data, where, **kw)
    return obj, details, fmt


def load(
    path: str | os.PathLike, format: str | None = None, hint: ReadHint | None = None
) -> PointCloud | TriangleMesh | Grid:
    """Read ``path`` (``-``: stdin) in the format its suffix (or ``format``) names.

    Points (vertices) with a NaN or infinite coordinate are dropped and counted in the
    object's ``invalid_dropped`` (:func:`read_report` says so). ``hint``: what the stage that
    reads the file keeps (:func:`load_detailed`).

    Raises
    ------
    InputError
        Malformed file (the message names the file and the line or byte), or every point
        of it invalid.
    ParameterError
        Unknown suffix or format, or a missing optional extra.
    """
    return check_read(load_detailed(path, format, hint)[0], path)


def check_read(obj: Any, path: str | os.PathLike) -> Any:
    """``obj``, refused when the reader dropped every one of its points as invalid."""
    dropped = getattr(obj, "invalid_dropped", 0)
    if dropped and len(obj.points) == 0:
        raise InputError(
            f"all {dropped} points have a NaN or infinite coordinate: nothing to read",
            "<stdin>" if str(path) == "-" else str(path),
        )
    return obj


def read_report(obj: Any, details: dict | None = None) -> dict | None:
    """What reading ``obj`` did that a report must show, or None when there is nothing to say.

    Keys: ``invalid_dropped`` (points with a NaN or infinite coordinate, dropped),
    ``organized`` (``"640x480"``: the width x height of the image(s) the points came from),
    ``window`` (a COPC file read in part: the reader's ``details["window"]``) and ``kept``
    (the points read).
    """
    if not isinstance(obj, (PointCloud, TriangleMesh)):
        return None
    dropped = int(getattr(obj, "invalid_dropped", 0))
    pixels = getattr(obj, "pixels", None)
    window = (details or {}).get("window")
    if not dropped and pixels is None and window is None:
        return None
    out: dict[str, Any] = {"kept": len(obj.points), "invalid_dropped": dropped}
    if pixels is not None:
        out["organized"] = pixels.describe()
    if window is not None:
        out["window"] = window
    return out


def save(
    obj: Any,
    path: str | os.PathLike,
    ascii: bool = False,
    format: str | None = None,
    points_only: bool = False,
) -> None:
    """Write a stage output atomically in the format the suffix of ``path`` (or ``format``) names.

    ``-`` and names without a suffix get PLY (grids ``.npz``).

    A mesh written to a format that holds points only is refused unless ``points_only``
    (then its vertices are written and a warning says the faces were dropped); a cloud is
    refused by STL.
    """
    where = "<stdout>" if str(path) == "-" else str(path)
    from recon_cli.io.tiles import Tileset

    if isinstance(obj, Tileset):
        if format:
            raise ParameterError(f"{where}: a tileset is a folder of GLB tiles: no --format")
        obj.write(path)
        return
    fmt = format_of(path, format)
    if isinstance(obj, Grid):
        if fmt is not None and fmt.name != "npz":
            raise ParameterError(f"{where}: a grid is written as .npz, not {fmt.name.upper()}")
        write_grid(obj, path)
        return
    fmt = fmt or FORMATS["ply"]
    obj = _fit_for(obj, fmt, where, points_only)
    _write_as(fmt.name, obj, path, ascii, (format or "").lower().lstrip("."))


def _fit_for(obj: Any, fmt: Any, where: str, points_only: bool) -> Any:
    """``obj`` as ``fmt`` can hold it (a mesh's vertices with ``points_only``), or refused."""
    if fmt.holds == "grid":
        raise ParameterError(
            f"{where}: .npz holds grids; a {_kind(obj)} is written as PLY, OBJ, ... ({supported()})"
        )
    if not fmt.writes:
        raise ParameterError(f"{where}: recon reads {fmt.name.upper()} but does not write it")
    if fmt.holds == "points" and isinstance(obj, TriangleMesh):
        if not points_only:
            raise ParameterError(
                f"{where}: {fmt.name.upper()} holds points only; the mesh's {len(obj.faces)} "
                "faces would be dropped "
                "(pass --points-only to write its vertices)"
            )
        from recon_cli.io.text import warn

        warn(
            f"{where}: {fmt.name.upper()} holds points only: wrote the {len(obj.vertices)} "
            f"vertices, dropped {len(obj.faces)} faces"
        )
        obj = obj.to_point_cloud()
    if fmt.holds == "triangles" and not isinstance(obj, TriangleMesh):
        raise ParameterError(
            f"{where}: {fmt.name.upper()} holds triangles; a point cloud cannot be written as "
            f"{fmt.name.upper()}"
        )
    return obj


def _write_as(name: str, obj: Any, path: str | os.PathLike, ascii: bool, given: str) -> None:
    """Write ``obj`` with format ``name``'s writer (``given``: the --format asked for, or "")."""
    if name == "ply":
        write_ply(obj, path, ascii=ascii)
    elif name == "obj":
        from recon_cli.io.obj import write_obj

        write_obj(obj, path)
    elif name == "off":
        from recon_cli.io.off import write_off

        write_off(obj, path)
    elif name == "stl":
        from recon_cli.io.stl import write_stl

        write_stl(obj, path, ascii=ascii)
    elif name == "xyz":
        from recon_cli.io.xyz import write_xyz

        write_xyz(obj, path, csv=str(path).lower().endswith(".csv") or given == "csv")
    elif name == "pcd":
        from recon_cli.io.pcd import write_pcd

        write_pcd(obj, path, data="ascii" if ascii else "binary")
    elif name == "gltf":
        from recon_cli.io.gltf import write_gltf

        binary = given == "glb" if given else not str(path).lower().endswith(".gltf")
        write_gltf(obj, path, binary=binary)
    elif name == "las":
        from recon_cli.io.las import write_las

        write_las(obj, path, compress=str(path).lower().endswith(".laz") or given == "laz")
    else:  # pragma: no cover - every writing format is listed above
        raise ParameterError(f"no writer for {name}")


def check_destination(path: str | os.PathLike, kinds: tuple[str, ...] = ()) -> None:
    """Refuse an output path before any work: a new folder for a tileset, else a file path."""
    from recon_cli.io.atomic import check_new_folder, check_output

    (check_new_folder if "tileset" in kinds else check_output)(path)


def _kind(obj: Any) -> str:
    return "mesh" if isinstance(obj, TriangleMesh) else "point cloud"

"""Helpers shared by the text formats (OBJ, OFF, XYZ, PCD ascii).

Rows of numbers, error positions, colour and number formatting.
"""

from __future__ import annotations

import logging

import numpy as np

from recon_cli.errors import InputError, ParameterError

log = logging.getLogger("recon")


def where_of(path) -> str:
    """How a file is named in messages (``-``: ``<stdin>``)."""
    return "<stdin>" if path is None or str(path) == "-" else str(path)


def as_uint8(data) -> np.ndarray:
    """The bytes of a file as a writable ``(n,) uint8`` array.

    No copy of a writable buffer (a file read by :func:`recon_cli.io.ply.read_bytes`); read-only
    data (``bytes``) is copied once, so the kernels see one array type whatever the bytes came
    from and what ``recon warmup`` compiled serves stdin and a library caller's ``bytes`` too (a
    read-only array is another numba signature: minutes of compiling for a copy of milliseconds).
    """
    if isinstance(data, np.ndarray):
        buf = data.view(np.uint8).reshape(-1)
    else:
        buf = np.frombuffer(data, dtype=np.uint8)
    return buf if buf.flags.writeable else buf.copy()


def line_at(buf: np.ndarray, offset: int) -> int:
    """1-based line number of byte ``offset``."""
    return int(np.count_nonzero(buf[:offset] == 10)) + 1


def token_at(buf: np.ndarray, offset: int) -> str:
    """The white-space-delimited token at byte ``offset`` (at most 40 characters) for a message."""
    end = offset
    n = len(buf)
    while end < n and end - offset < 40 and buf[end] not in (9, 10, 13, 32, 44, 59):
        end += 1
    return bytes(buf[offset:end]).decode("latin-1")


def bad_number(buf: np.ndarray, offset: int, where: str) -> InputError:
    """The error for the token at byte ``offset``: not a number, or a value missing."""
    tok = token_at(buf, offset)
    what = f"{tok!r} is not a number" if tok else "a value is missing"
    return InputError(f"line {line_at(buf, offset)}: {what}", where)


def slow_values(buf: np.ndarray, spans: np.ndarray) -> np.ndarray:
    """The values of the tokens ``buf[s:e]`` for the rows of ``spans`` ((k, 2)) by ``float``.

    These are the few numbers the kernel's exact fast paths leave undecided.
    """
    raw = buf.tobytes() if len(spans) > 64 else None
    out = np.empty(len(spans), np.float64)
    for r, (s, e) in enumerate(np.asarray(spans, dtype=np.int64).tolist()):
        out[r] = float(raw[s:e] if raw is not None else bytes(buf[s:e]))
    return out


def _run_rows(
    buf: np.ndarray,
    start: int,
    end: int,
    where: str,
    delim: int,
    comment: int,
    cap: int,
    fixed: bool,
):
    from recon_cli.io._text_kernel import parse_rows

    out = parse_rows(buf, start, end, delim, comment, max(16, cap), fixed)
    values, nvals, row_start, row_line, nrows, ncol, slow, nslow, err, at, bad_count = out
    if err == 1:
        raise bad_number(buf, at, where)
    if err == 2:
        raise InputError(
            f"line {line_at(buf, at)}: {bad_count} columns, the first row has {ncol}", where
        )
    values = values[:nvals]
    if nslow:
        slow = slow[:nslow]
        values[slow[:, 0]] = slow_values(buf, slow[:, 1:])
    return values, row_start[: nrows + 1], row_line[:nrows], nrows, ncol


def read_rows(buf: np.ndarray, start: int, end: int, where: str, delim: int = 0, comment: int = 35):
    """The rows of numbers in ``buf[start:end]``: ``(values, row_start, row_line)``.

    ``values`` (float64) holds every row's numbers one after the other, row r being
    ``values[row_start[r]:row_start[r + 1]]``; ``row_line`` gives each row's line number
    counted from ``start`` (1-based). Blank lines and lines starting with ``comment`` are
    skipped. A token that is not a number raises :class:`InputError` naming its line.
    """
    values, row_start, row_line, _, _ = _run_rows(
        buf, start, end, where, delim, comment, (end - start) // 8, False
    )
    return values, row_start, row_line


def read_table(
    buf: np.ndarray,
    start: int,
    end: int,
    where: str,
    delim: int = 0,
    comment: int = 35,
    cap: int = 0,
):
    """The rows of numbers in ``buf[start:end]`` as an ``(n, k)`` float64 table.

    Every row must have the first row's ``k`` fields (else :class:`InputError` naming the line).
    ``cap`` is a guess of the number of values (0: from the size); the table is a view of an array
    that may be somewhat larger. Blank lines and ``comment`` lines are skipped as in
    :func:`read_rows`.
    """
    values, _, _, nrows, ncol = _run_rows(
        buf, start, end, where, delim, comment, cap or (end - start) // 8, True
    )
    return values.reshape(nrows, max(ncol, 0))


def check_finite(points: np.ndarray, where: str, what: str = "vertex") -> None:
    """Raise an :class:`~recon_cli.errors.InputError` naming the first non-finite row."""
    ok = np.isfinite(points).all(axis=1)
    if not ok.all():
        raise InputError(f"{what} {int(np.argmin(ok))} has a NaN or infinite coordinate", where)


# the quiet bit of a NaN (the mantissa's highest) by float size in bytes
_QUIET_BIT = {2: 1 << 9, 4: 1 << 22, 8: 1 << 51}


def quiet_nans(values: np.ndarray) -> np.ndarray:
    """``values``, or a copy with its signalling NaNs made quiet when it holds any.

    Floats read as raw bytes may hold signalling NaNs, which raise numpy's "invalid value"
    warning when cast or computed with; other dtypes are returned as they are.
    """
    quiet = _QUIET_BIT.get(values.dtype.itemsize)
    if values.dtype.kind != "f" or quiet is None:
        return values
    nan = np.isnan(values)  # isnan does not signal
    if not nan.any():
        return values
    loud = nan & ((values.view(f"u{values.dtype.itemsize}") & quiet) == 0)
    if loud.any():
        values = values.copy()
        values[loud] = np.nan
    return values


def check_header_words(names, fmt: str, where: str, taken=()) -> None:
    """Refuse an attribute name that cannot be a word of a ``fmt`` header (PLY, PCD).

    Such a header is ASCII words: a name with a space or another character would write a file
    no reader takes, and one of the ``taken`` names (the coordinates', normals', colours' the
    writer puts in) a field twice. Raises :class:`~recon_cli.errors.ParameterError` naming
    ``where``.
    """
    for name in names:
        if name in taken:
            raise ParameterError(
                f"{where}: attribute {ascii(name)} has the name of a {fmt} field written for the "
                "coordinates, normals or colours; write another format"
            )
        if not (name and name.isascii() and name.isprintable() and " " not in name):
            raise ParameterError(
                f"{where}: attribute {ascii(name)} cannot be a {fmt} field name (one word of "
                "printable ASCII); write another format"
            )


def colours_from_unit(c: np.ndarray) -> np.ndarray:
    """Colours given as floats: uint8 when every value is k/255, otherwise the floats as given.

    Our writers put uint8 colours as k/255.
    """
    if c.size and c.min() >= 0 and c.max() <= 1:
        q = np.rint(c * 255)
        if np.all(np.abs(q / 255 - c) <= 1e-6):
            return q.astype(np.uint8)
    return c


def colours_to_unit(c: np.ndarray) -> np.ndarray:
    """Colours as floats in 0..1 (integer colours divided by their type's maximum)."""
    if c.dtype.kind in "ui":
        return c.astype(np.float64) / float(np.iinfo(c.dtype).max)
    return c.astype(np.float64)


# a comment line our text writers put first when the coordinates are float32: the reader
# then returns float32 coordinates (and normals), exactly those written (``%.9g`` round-trips
# float32), instead of the nearest doubles of the printed decimals
FLOAT32_MARK = "recon: float32"


def float32_marked(history: list[str]) -> tuple[bool, list[str]]:
    """(whether ``history`` holds the float32 mark, the history without it)."""
    rest = [h for h in history if h != FLOAT32_MARK]
    return len(rest) != len(history), rest


def apply_float32_mark(obj, history: list[str]):
    """``obj`` with float32 coordinates and normals when ``history`` holds the mark.

    Sets its history.
    """
    marked, rest = float32_marked(history)
    obj.history = rest
    if marked:
        pts = np.ascontiguousarray(obj.points, dtype=np.float32)
        if hasattr(obj, "faces"):
            obj.vertices = pts
        else:
            obj.points = pts
        if obj.normals is not None:
            obj.normals = np.ascontiguousarray(obj.normals, dtype=np.float32)
        obj.point_dtype = np.float32
    return obj


def one_line(line: str) -> str:
    """``line`` as printable ASCII on one line: any other character as its Python escape.

    History lines come from files (an STL's name, a PLY comment, a glTF string) and go into
    headers and comment lines, where a newline would end the line and a byte above 127 is not
    ASCII.
    """
    if line.isascii() and line.isprintable():
        return line
    return "".join(
        c if " " <= c <= "~" else c.encode("unicode_escape").decode("ascii") for c in line
    )


def mark_lines(obj, prefix: str = "# ") -> str:
    """The float32 mark line (when ``obj`` is float32) and the history, as comment lines."""
    lines = [FLOAT32_MARK] if np.dtype(obj.point_dtype) == np.float32 else []
    return "".join(f"{prefix}{one_line(h)}\n" for h in lines + list(obj.history))


def float_format(dtype) -> str:
    """``%.9g`` for float32 values (enough to round-trip them), ``%.17g`` otherwise."""
    return "%.9g" if np.dtype(dtype) == np.float32 else "%.17g"


def format_rows(template: str, table: np.ndarray, chunk: int = 1 << 16) -> bytes:
    """``template % row`` for every row of ``table`` ((n, k), numbers), joined, as bytes."""
    n = len(table)
    out = []
    for s in range(0, n, chunk):
        part = table[s : s + chunk]
        out.append(((template * len(part)) % tuple(part.ravel().tolist())).encode("ascii"))
    return b"".join(out)


def warn(message: str) -> None:
    """A one-line warning on stderr (``recon: warning: ...``)."""
    log.warning("warning: %s", message)

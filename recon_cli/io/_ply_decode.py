"""The body of a PLY file decoded into its elements' arrays: binary and ASCII.

Binary rows are numpy structured records (views of the file's bytes when no list varies in
length); ASCII rows are checked line by line for their number of values. Every count is checked
against the bytes present before anything is allocated.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.aot import kernels
from recon_cli.errors import InputError
from recon_cli.io._ply_types import PlyData, PlyElement, PlyProperty, ply_name


def memory_of(buf: bytes | np.ndarray) -> memoryview:
    """A memoryview of a file's bytes, or of the uint8 array that holds them (see read_bytes)."""
    # numpy's stubs declare the buffer protocol from Python 3.12 on only
    return buf.data if isinstance(buf, np.ndarray) else memoryview(buf)


def parse_binary_body(
    ply: PlyData, buf: bytes | np.ndarray, offset: int, order: str, where: str
) -> None:
    mv = memory_of(buf)
    for el in ply.elements:
        remaining = len(buf) - offset
        fixed = sum(
            np.dtype(p.count_dtype if p.is_list else p.dtype).itemsize for p in el.properties
        )
        # every row needs at least its scalars and list counts: check before allocating
        if el.count and (fixed == 0 or el.count > remaining // max(fixed, 1)):
            if fixed == 0:
                raise InputError(
                    f"element {el.name!r} has no properties but {el.count} rows", where
                )
            raise InputError(
                f"truncated: header declares {el.count} {el.name!r} rows "
                f"(at least {el.count * fixed} bytes) but only {remaining} bytes remain",
                where,
            )
        if not any(p.is_list for p in el.properties):
            dt = np.dtype([(p.name, order + p.dtype) for p in el.properties])
            arr = np.frombuffer(mv, dtype=dt, count=el.count, offset=offset)
            # views into the file's bytes; consumers copy what they keep (one pass, not two)
            el.data = {p.name: arr[p.name] for p in el.properties}
            el.raw = arr
            offset += dt.itemsize * el.count
            continue
        offset = _parse_binary_lists(el, buf, mv, offset, order, where)
    # extra bytes after the last element are tolerated (some writers pad), never read


def _parse_binary_lists(
    el: PlyElement, buf: bytes | np.ndarray, mv: memoryview, offset: int, order: str, where: str
) -> int:
    """Decode an element holding list properties; returns the new offset."""
    if el.count == 0:
        el.data = {
            p.name: (np.zeros((0, 0), p.dtype) if p.is_list else np.zeros(0, p.dtype))
            for p in el.properties
        }
        return offset
    # fast path: read the first row's list lengths and assume every row has the same
    ks = _first_row_counts(el, buf, offset, order, where)
    fields: list[tuple[Any, ...]] = []
    for p in el.properties:
        if p.is_list:
            fields.append((p.name + "\0n", f"{order}{p.count_dtype}"))
            if ks[p.name] > 0:
                fields.append((p.name, order + p.dtype, (ks[p.name],)))
        else:
            fields.append((p.name, order + p.dtype))
    dt = np.dtype(fields)
    if offset + dt.itemsize * el.count <= len(buf):
        arr = np.frombuffer(mv, dtype=dt, count=el.count, offset=offset)
        if all(np.all(arr[p.name + "\0n"] == ks[p.name]) for p in el.properties if p.is_list):
            data: dict[str, np.ndarray] = {}
            for p in el.properties:
                if p.is_list:
                    k = ks[p.name]
                    data[p.name] = (
                        arr[p.name].astype(np.dtype(p.dtype)).reshape(el.count, k)
                        if k > 0
                        else np.zeros((el.count, 0), np.dtype(p.dtype))
                    )
                else:
                    data[p.name] = arr[p.name].astype(np.dtype(p.dtype))
            el.data = data
            return offset + dt.itemsize * el.count
    return _parse_binary_lists_general(el, buf, offset, order, where)


def _first_row_counts(
    el: PlyElement, buf: bytes | np.ndarray, offset: int, order: str, where: str
) -> dict[str, int]:
    ks: dict[str, int] = {}
    pos = offset
    for p in el.properties:
        if p.is_list:
            cdt = np.dtype(f"{order}{p.count_dtype}")
            if pos + cdt.itemsize > len(buf):
                raise InputError(f"truncated in element {el.name!r}", where)
            k = int(np.frombuffer(buf, cdt, 1, pos)[0])
            if k < 0:
                raise InputError(f"negative list length {k} in element {el.name!r}", where)
            if pos + cdt.itemsize + k * np.dtype(p.dtype).itemsize > len(buf):
                raise InputError(
                    f"truncated: the first {el.name!r} row's {p.name!r} list has length {k}, "
                    f"longer than the {len(buf) - pos} bytes left",
                    where,
                )
            ks[p.name] = k
            pos += cdt.itemsize + k * np.dtype(p.dtype).itemsize
        else:
            pos += np.dtype(p.dtype).itemsize
    return ks


def _parse_binary_lists_general(
    el: PlyElement, buf: bytes | np.ndarray, offset: int, order: str, where: str
) -> int:
    """Rows of differing list lengths: one pass over the rows to find their offsets.

    Only lists with mixed lengths (e.g. a mesh of triangles and quads) come here.
    """
    K = kernels("recon_cli.io._ply_kernel")
    scan_list_rows = K.scan_list_rows

    layout = []  # per property: (is_list, count size, item size, count signed)
    for p in el.properties:
        if p.is_list:
            c = np.dtype(p.count_dtype)
            layout.append((1, c.itemsize, np.dtype(p.dtype).itemsize, 1 if c.kind == "i" else 0))
        else:
            layout.append((0, 0, np.dtype(p.dtype).itemsize, 0))
    lay = np.asarray(layout, dtype=np.int64)
    raw = np.frombuffer(buf, dtype=np.uint8)
    big = order == ">"
    # starts[row, prop] = byte offset of the property (of its count for a list); lens[row, prop] =
    # list length
    starts, lens, end, err = scan_list_rows(raw, offset, el.count, lay, big)
    if err == 1:
        raise InputError(f"truncated in element {el.name!r}", where)
    if err == 2:
        raise InputError(f"negative list length in element {el.name!r}", where)
    data: dict[str, np.ndarray] = {}
    for j, p in enumerate(el.properties):
        if p.is_list:
            item = np.dtype(order + p.dtype)
            cs = np.dtype(p.count_dtype).itemsize
            k = lens[:, j]
            # gather every item: position of item i of row r is starts[r]+cs+i*itemsize
            total = int(k.sum())
            row_of = np.repeat(np.arange(el.count), k)
            first = np.cumsum(k) - k
            within = np.arange(total) - np.repeat(first, k)
            pos = starts[row_of, j] + cs + within * item.itemsize
            idx = pos[:, None] + np.arange(item.itemsize)[None, :]
            items = raw[idx].copy().view(item).reshape(-1).astype(np.dtype(p.dtype))
            out = np.empty(el.count, dtype=object)
            for r, piece in enumerate(np.split(items, np.cumsum(k)[:-1])):
                out[r] = piece
            data[p.name] = out
        else:
            item = np.dtype(order + p.dtype)
            idx = starts[:, j][:, None] + np.arange(item.itemsize)[None, :]
            data[p.name] = raw[idx].copy().view(item).reshape(-1).astype(np.dtype(p.dtype))
    el.data = data
    return int(end)


def parse_ascii_body(ply: PlyData, buf: bytes | np.ndarray, offset: int, where: str) -> None:
    """Decode an ASCII body: one element row per line, every line checked for its number of values.

    A row with a value too many or too few would shift every later value (a silently wrong
    cloud), so each line must hold exactly its row's values; blank lines are skipped, and
    lines after the last element are an error.
    """
    K = kernels("recon_cli.io._ply_kernel")
    ascii_line_tokens = K.ascii_line_tokens

    body = bytes(memory_of(buf)[offset:])
    tokens = body.split()
    head = bytes(memory_of(buf)[:offset])
    # file line number of the body's first line
    first = head.count(b"\n") + head.count(b"\r") - head.count(b"\r\n") + 1
    per_line = ascii_line_tokens(np.frombuffer(body, dtype=np.uint8))
    lines = np.flatnonzero(per_line)  # the lines that hold values, in order
    counts = per_line[lines]
    row = 0  # index into lines
    pos = 0  # index into tokens
    for el in ply.elements:
        nprop = len(el.properties)
        if el.count and nprop == 0:
            raise InputError(f"element {el.name!r} has no properties but {el.count} rows", where)
        if el.count > len(lines) - row:
            raise InputError(
                f"truncated: header declares {el.count} {el.name!r} rows but only "
                f"{len(lines) - row} lines of values remain",
                where,
            )
        el_lines = lines[row : row + el.count] + first
        el_counts = counts[row : row + el.count]
        if not any(p.is_list for p in el.properties):
            bad = np.flatnonzero(el_counts != nprop)
            if bad.size:
                i = int(bad[0])
                raise InputError(
                    f"line {int(el_lines[i])}: {el.name!r} row {i} has {int(el_counts[i])} "
                    f"values, expected {nprop}",
                    where,
                )
            block = tokens[pos : pos + el.count * nprop]
            pos += el.count * nprop
            table = _ascii_values(block, where, el.name).reshape(el.count, nprop)
            el.data = {
                p.name: _cast(table[:, j], p.dtype, where, el.name)
                for j, p in enumerate(el.properties)
            }
        else:
            pos = _parse_ascii_lists(el, tokens, pos, el_counts, el_lines, where)
        row += el.count
    if row < len(lines):
        raise InputError(
            f"line {int(lines[row] + first)}: values after the last element "
            f"({len(lines) - row} more lines than the header declares)",
            where,
        )


def _ascii_values(block: list[bytes], where: str, name: str) -> np.ndarray:
    if not block:
        return np.zeros(0, dtype=np.float64)
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return np.array(block).astype(np.float64)
    except ValueError:
        bad = next((t for t in block if not _is_number(t)), block[0])
        raise InputError(
            f"element {name!r}: {bad[:40].decode('ascii', 'replace')!r} is not a number", where
        ) from None


def _is_number(tok: bytes) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _cast(values: np.ndarray, code: str, where: str, name: str) -> np.ndarray:
    """``values`` (float64) in the property's type; a value the type cannot hold is an error."""
    dt = np.dtype(code)
    if dt.kind in "iu":
        finite = np.isfinite(values)
        if not finite.all() or np.any(values != np.round(values)):
            raise InputError(f"element {name!r}: non-integer value for an integer property", where)
        info = np.iinfo(dt)
        if values.size and (values.min() < info.min or values.max() > info.max):
            raise InputError(f"element {name!r}: value out of range for {ply_name(dt)}", where)
    elif dt.itemsize < 8 and values.size:
        big = np.abs(values[np.isfinite(values)])
        if big.size and big.max() > np.finfo(dt).max:
            raise InputError(
                f"element {name!r}: value {big.max():g} out of range for {ply_name(dt)}", where
            )
    return values.astype(dt)


def _parse_ascii_lists(
    el: PlyElement, tokens: list[bytes], pos: int, counts: np.ndarray, lines: np.ndarray, where: str
) -> int:
    """Rows holding lists; ``counts[i]`` values on file line ``lines[i]`` make row i."""
    props = el.properties
    if el.count == 0:
        el.data = {
            p.name: (np.zeros((0, 0), p.dtype) if p.is_list else np.zeros(0, p.dtype))
            for p in props
        }
        return pos
    # fast path (faces): one list, first, then scalars; every line of one length with matching
    # counts
    if props[0].is_list and not any(p.is_list for p in props[1:]) and np.all(counts == counts[0]):
        end = _uniform_lists(el, tokens, pos, int(counts[0]), where)
        if end is not None:
            return end
    # rows one by one (ASCII is not the fast format)
    cols: dict[str, list] = {p.name: [] for p in props}
    for i in range(el.count):
        pos = _ascii_row(
            el, tokens, pos, pos + int(counts[i]), cols, f"line {int(lines[i])}", i, where
        )
    el.data = {p.name: _ascii_column(el, p, cols[p.name], where) for p in props}
    return pos


def _uniform_lists(
    el: PlyElement, tokens: list[bytes], pos: int, width: int, where: str
) -> int | None:
    """Rows of ``width`` values, a list first whose count is the same in every row.

    Decoded as one table; None (nothing decoded) when some row's count differs.
    """
    props = el.properties
    k = width - len(props)  # items per list
    block = tokens[pos : pos + el.count * width]
    table = _ascii_values(block, where, el.name).reshape(el.count, width)
    if k < 0 or not np.all(table[:, 0] == k):
        return None
    vals = _cast(table[:, 1 : 1 + k].reshape(-1), props[0].dtype, where, el.name)
    data: dict[str, np.ndarray] = {props[0].name: vals.reshape(el.count, k)}
    for j, p in enumerate(props[1:]):
        data[p.name] = _cast(table[:, 1 + k + j], p.dtype, where, el.name)
    el.data = data
    return pos + el.count * width


def _ascii_row(
    el: PlyElement, tokens: list[bytes], pos: int, end: int, cols: dict, at: str, i: int, where: str
) -> int:
    """Row ``i``, the tokens ``pos:end`` of one line (``at``), appended to ``cols``; the end."""
    for p in el.properties:
        if pos >= end:
            raise InputError(f"{at}: {el.name!r} row {i} ends before its {p.name!r} value", where)
        if not p.is_list:
            cols[p.name].append(tokens[pos])
            pos += 1
            continue
        try:
            k = int(tokens[pos])
        except ValueError:
            raise InputError(
                f"{at}: bad list length {tokens[pos][:20].decode('ascii', 'replace')!r}", where
            ) from None
        if k < 0 or pos + 1 + k > end:
            raise InputError(
                f"{at}: list length {k} but the line holds {end - pos - 1} more values", where
            )
        cols[p.name].append(tokens[pos + 1 : pos + 1 + k])
        pos += 1 + k
    if pos != end:
        raise InputError(
            f"{at}: {el.name!r} row {i} has {end - pos} values more than its properties", where
        )
    return pos


def _ascii_column(el: PlyElement, p: PlyProperty, values: list, where: str) -> np.ndarray:
    """Property ``p``'s tokens, one per row (a list of tokens per row for a list), as an array."""
    if not p.is_list:
        return _cast(_ascii_values(values, where, el.name), p.dtype, where, el.name)
    lengths = {len(r) for r in values}
    if len(lengths) <= 1:
        k = lengths.pop() if lengths else 0
        flat = [t for r in values for t in r]
        vals = _cast(_ascii_values(flat, where, el.name), p.dtype, where, el.name)
        return vals.reshape(len(values), k)
    out = np.empty(len(values), dtype=object)
    for i, r in enumerate(values):
        out[i] = _cast(_ascii_values(r, where, el.name), p.dtype, where, el.name)
    return out

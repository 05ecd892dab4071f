"""The glTF 2.0 document of a ``.glb`` or ``.gltf`` file: its JSON checked, buffers and accessors.

Every value read from the JSON is checked for its type and range before it is used (a fuzzed
file is refused in one line naming the JSON path, never a ``KeyError`` or a huge allocation):
indices into the arrays, counts against the bytes the buffer holds, strides, component types.
:mod:`recon_cli.io.gltf` builds the data model from what this module returns.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import os
import struct
import urllib.parse
from typing import Any

import numpy as np

from recon_cli.errors import InputError

GLB_MAGIC = b"glTF"
JSON_CHUNK = 0x4E4F534A
BIN_CHUNK = 0x004E4942

#: componentType -> numpy dtype (little-endian)
COMPONENTS: dict[int, np.dtype] = {
    5120: np.dtype("i1"),
    5121: np.dtype("u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
#: accessor type -> components per element
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# an accessor with no bufferView is zeros: refused beyond this many bytes per byte of the file
_ZEROS_PER_BYTE = 64


def _kind(v: Any) -> str:
    """What a JSON value is, for a message (a short repr)."""
    text = (
        json.dumps(v) if isinstance(v, (int, float, str, bool)) or v is None else type(v).__name__
    )
    return text if len(text) <= 40 else text[:37] + "..."


class Document:
    """A parsed glTF file: the JSON object, its buffers (loaded on first use) and checked getters.

    Parameters
    ----------
    data : (n,) uint8
        The file's bytes (GLB or JSON).
    where : str
        The file's name for messages; relative buffer URIs are resolved in its folder
        (``<stdin>``: none can be).
    """

    def __init__(self, data: np.ndarray, where: str):
        self.where = where
        self.binary = bytes(data[:4]) == GLB_MAGIC
        self.bin_chunk: np.ndarray | None = None
        if self.binary:
            text = self._glb_chunks(data)
        else:
            text = bytes(data)
        self.json = self._parse_json(text)
        self._buffers: dict[int, np.ndarray] = {}
        self.nbytes = len(data)

    # -- errors and typed getters
    def fail(self, message: str) -> InputError:
        """The one-line error naming the file."""
        return InputError(message, self.where)

    def _glb_chunks(self, data: np.ndarray) -> bytes:
        """The JSON text of a GLB, its BIN chunk kept in ``bin_chunk``."""
        size = len(data)
        if size < 20:
            raise self.fail(f"truncated: a GLB needs at least 20 bytes, the file has {size}")
        version, length = struct.unpack_from("<II", bytes(data[4:12]))
        if version != 2:
            raise self.fail(f"GLB version {version}: recon reads glTF 2.0")
        if length != size:
            raise self.fail(f"GLB header declares {length} bytes but the file has {size}")
        pos = 12
        chunks: list[tuple[int, int, int]] = []
        while pos < size:
            if pos + 8 > size:
                raise self.fail(f"truncated: chunk header at byte {pos} runs past the end")
            clen, ctype = struct.unpack_from("<II", bytes(data[pos : pos + 8]))
            if clen > size - pos - 8:
                raise self.fail(
                    f"chunk at byte {pos} declares {clen} bytes, more than the {size - pos - 8} "
                    "left"
                )
            chunks.append((ctype, pos + 8, clen))
            pos += 8 + clen
        if not chunks or chunks[0][0] != JSON_CHUNK:
            raise self.fail("the first GLB chunk is not JSON")
        if len(chunks) > 1 and chunks[1][0] == BIN_CHUNK:
            _, start, clen = chunks[1]
            self.bin_chunk = data[start : start + clen]
        _, start, clen = chunks[0]
        return bytes(data[start : start + clen])

    def _parse_json(self, text: bytes) -> dict:
        def refuse_constant(name: str) -> Any:
            raise ValueError(f"{name} is not JSON")

        try:
            doc = json.loads(text.decode("utf-8-sig"), parse_constant=refuse_constant)
        except UnicodeDecodeError:
            raise self.fail("the glTF JSON is not UTF-8 text") from None
        except RecursionError:
            raise self.fail("the glTF JSON is nested too deeply") from None
        except ValueError as exc:  # JSONDecodeError, NaN constants, integers of 4,300+ digits
            raise self.fail(f"not valid glTF JSON ({str(exc).splitlines()[0]})") from None
        if not isinstance(doc, dict):
            raise self.fail("the glTF JSON is not an object")
        asset = doc.get("asset")
        if not isinstance(asset, dict) or not isinstance(asset.get("version"), str):
            raise self.fail("the glTF JSON has no asset.version")
        if not asset["version"].startswith("2."):
            raise self.fail(f"glTF version {asset['version'][:20]!r}: recon reads glTF 2.0")
        return doc

    def items(self, name: str) -> list:
        """The top-level array ``name`` (empty when absent), each item an object."""
        arr = self.json.get(name, [])
        if not isinstance(arr, list) or not all(isinstance(x, dict) for x in arr):
            raise self.fail(f"{name} must be an array of objects")
        return arr

    def item(self, name: str, index: Any, at: str) -> dict:
        """``json[name][index]``, the index checked (``at`` names where it was read)."""
        arr = self.items(name)
        if type(index) is not int or not 0 <= index < len(arr):
            raise self.fail(f"{at}: {_kind(index)} is not an index into {name} ({len(arr)} items)")
        return arr[index]

    def integer(self, obj: dict, key: str, at: str, default: int | None = None, lo: int = 0) -> int:
        """``obj[key]``, an integer of at least ``lo`` (``default`` when absent, else required)."""
        v = obj.get(key, default)
        if v is None:
            raise self.fail(f"{at}.{key} is missing")
        if type(v) is not int or v < lo:
            raise self.fail(f"{at}.{key}: expected an integer >= {lo}, got {_kind(v)}")
        return v

    def numbers(self, v: Any, n: int, at: str) -> np.ndarray:
        """``v`` as ``n`` finite float64 numbers."""
        if (
            not isinstance(v, list)
            or len(v) != n
            or not all(type(x) in (int, float) and math.isfinite(x) for x in v)
        ):
            raise self.fail(f"{at}: expected {n} finite numbers, got {_kind(v)}")
        return np.array(v, dtype=np.float64)

    # -- buffers
    def buffer(self, index: Any, at: str) -> np.ndarray:
        """The bytes of buffer ``index`` (GLB BIN chunk, a data: URI or a file beside the glTF)."""
        buf = self.item("buffers", index, at)
        if index in self._buffers:
            return self._buffers[index]
        here = f"buffers[{index}]"
        length = self.integer(buf, "byteLength", here, lo=1)
        uri = buf.get("uri")
        if uri is None:
            if not (self.binary and index == 0) or self.bin_chunk is None:
                raise self.fail(f"{here} has no uri and is not a GLB's BIN chunk (no data)")
            data = self.bin_chunk
        elif not isinstance(uri, str):
            raise self.fail(f"{here}.uri: expected a string, got {_kind(uri)}")
        elif uri.startswith("data:"):
            data = self._data_uri(uri, here)
        else:
            data = self._file_uri(uri, here, length)
        if len(data) < length:
            raise self.fail(f"{here} declares {length} bytes but holds {len(data)}")
        self._buffers[index] = data[:length]
        return self._buffers[index]

    def _data_uri(self, uri: str, here: str) -> np.ndarray:
        head, sep, payload = uri.partition(",")
        if not sep or not head.endswith(";base64"):
            raise self.fail(f"{here}.uri: a data: URI must be base64 (data:...;base64,...)")
        try:
            raw = base64.b64decode(payload, validate=True)
        except (binascii.Error, ValueError):
            raise self.fail(f"{here}.uri: the base64 data is malformed") from None
        return np.frombuffer(bytearray(raw), dtype=np.uint8)  # writable, as a file's bytes are

    def _file_uri(self, uri: str, here: str, length: int) -> np.ndarray:
        """A buffer in a file named relative to the glTF, which must stay inside its folder."""
        if self.where == "<stdin>":
            raise self.fail(
                f"{here}.uri {uri[:60]!r}: a glTF read from stdin can hold data: URIs only"
            )
        parsed = urllib.parse.urlsplit(uri)
        rel = urllib.parse.unquote(parsed.path)
        if parsed.scheme or parsed.netloc or rel.startswith("/") or "\0" in rel or not rel:
            raise self.fail(f"{here}.uri {uri[:60]!r}: only relative file names are read")
        folder = os.path.realpath(os.path.dirname(os.path.abspath(self.where)))
        target = os.path.realpath(os.path.join(folder, rel))
        if os.path.commonpath([folder, target]) != folder:
            raise self.fail(f"{here}.uri {uri[:60]!r} leads outside the glTF's folder")
        try:
            size = os.path.getsize(target)
            if size < length:
                raise self.fail(f"{here}: {rel} has {size} bytes, the buffer declares {length}")
            out = np.empty(length, np.uint8)
            with open(target, "rb") as f:
                got = f.readinto(out.data)
            if got != length:
                raise self.fail(f"{here}: {rel} ended after {got} of {length} bytes")
            return out
        except OSError as exc:
            raise self.fail(f"{here}: cannot read {rel} ({exc.strerror or exc})") from None

    def buffer_view(self, index: Any, at: str) -> tuple[np.ndarray, int | None]:
        """The bytes of bufferView ``index`` and its byteStride (None when not given)."""
        bv = self.item("bufferViews", index, at)
        here = f"bufferViews[{index}]"
        ext = bv.get("extensions")
        if isinstance(ext, dict) and {"EXT_meshopt_compression", "KHR_meshopt_compression"} & set(
            ext
        ):
            raise self.fail(f"{here} is meshopt-compressed: recon does not decode meshopt")
        buf = self.buffer(bv.get("buffer"), f"{here}.buffer")
        offset = self.integer(bv, "byteOffset", here, default=0)
        length = self.integer(bv, "byteLength", here, lo=1)
        if offset + length > len(buf):
            raise self.fail(
                f"{here} spans bytes {offset}..{offset + length} of a {len(buf)}-byte buffer"
            )
        stride = bv.get("byteStride")
        if stride is not None:
            stride = self.integer(bv, "byteStride", here, lo=4)
            if stride > 252 or stride % 4:
                raise self.fail(f"{here}.byteStride {stride}: must be a multiple of 4 in 4..252")
        return buf[offset : offset + length], stride

    # -- accessors
    def accessor(self, index: Any, at: str) -> tuple[np.ndarray, dict]:
        """Accessor ``index`` as an ``(count, width)`` array of its component type, and its JSON.

        A view of the buffer when it is a plain strided layout; sparse substitutions and
        accessors without a bufferView (zeros) give a new array.
        """
        acc = self.item("accessors", index, at)
        here = f"accessors[{index}]"
        ctype = acc.get("componentType")
        if type(ctype) is not int or ctype not in COMPONENTS:
            raise self.fail(f"{here}.componentType {_kind(ctype)} is not a glTF component type")
        dtype = COMPONENTS[ctype]
        kind = acc.get("type")
        if not isinstance(kind, str) or kind not in WIDTHS:
            raise self.fail(f"{here}.type {_kind(kind)} is not a glTF accessor type")
        if kind.startswith("MAT"):
            raise self.fail(f"{here} is a {kind} accessor: recon reads scalars and vectors")
        width = WIDTHS[kind]
        count = self.integer(acc, "count", here, lo=1)
        elem = width * dtype.itemsize
        if "bufferView" in acc:
            view, stride = self.buffer_view(acc["bufferView"], f"{here}.bufferView")
            offset = self.integer(acc, "byteOffset", here, default=0)
            stride = stride or elem
            need = offset + stride * (count - 1) + elem
            if need > len(view):
                raise self.fail(
                    f"{here}: {count} elements of {elem} bytes (stride {stride}) from byte "
                    f"{offset} need {need} bytes; bufferView holds {len(view)}"
                )
            arr = np.ndarray(
                (count, width), dtype, buffer=view, offset=offset, strides=(stride, dtype.itemsize)
            )
        else:
            if count * elem > _ZEROS_PER_BYTE * max(self.nbytes, 1):
                raise self.fail(f"{here}: {count} elements without a bufferView (too many zeros)")
            arr = np.zeros((count, width), dtype)
        if "sparse" in acc:
            arr = self._sparse(arr, acc["sparse"], here)
        return arr, acc

    def _sparse(self, arr: np.ndarray, sparse: Any, here: str) -> np.ndarray:
        """``arr`` with the sparse substitutions of an accessor applied (a copy)."""
        at = f"{here}.sparse"
        if not isinstance(sparse, dict):
            raise self.fail(f"{at} must be an object")
        n = self.integer(sparse, "count", at, lo=1)
        if n > len(arr):
            raise self.fail(f"{at}.count {n} exceeds the accessor's {len(arr)} elements")
        ind, val = sparse.get("indices"), sparse.get("values")
        if not isinstance(ind, dict) or not isinstance(val, dict):
            raise self.fail(f"{at} needs indices and values objects")
        ctype = ind.get("componentType")
        if ctype not in (5121, 5123, 5125) or type(ctype) is not int:
            raise self.fail(f"{at}.indices.componentType {_kind(ctype)} is not an unsigned type")
        idx = self._packed(ind, COMPONENTS[ctype], n, 1, f"{at}.indices")[:, 0].astype(np.int64)
        if (np.diff(idx) <= 0).any() or idx[-1] >= len(arr):
            raise self.fail(f"{at}.indices must increase strictly and stay below {len(arr)}")
        values = self._packed(val, arr.dtype, n, arr.shape[1], f"{at}.values")
        out = np.array(arr)
        out[idx] = values
        return out

    def _packed(self, obj: dict, dtype: np.dtype, n: int, width: int, at: str) -> np.ndarray:
        """``n`` tightly packed elements at ``obj``'s bufferView and byteOffset."""
        view, _ = self.buffer_view(obj.get("bufferView"), f"{at}.bufferView")
        offset = self.integer(obj, "byteOffset", at, default=0)
        need = offset + n * width * dtype.itemsize
        if need > len(view):
            raise self.fail(f"{at}: {n} elements need {need} bytes; bufferView holds {len(view)}")
        return np.ndarray((n, width), dtype, buffer=view, offset=offset)

    def extensions_required(self) -> list[str]:
        """The file's ``extensionsRequired`` names."""
        req = self.json.get("extensionsRequired", [])
        if not isinstance(req, list) or not all(isinstance(x, str) for x in req):
            raise self.fail("extensionsRequired must be an array of strings")
        return req

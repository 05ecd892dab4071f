"""glTF 2.0 (``.glb`` binary, ``.gltf`` JSON): our own reader and writer (numpy, no glTF library).

Reading takes every triangle primitive (``TRIANGLES``; strips and fans are converted) of every
mesh node of the scene, each with its node's world transform applied in float64 (so a
translation holds a large offset exactly; ``CESIUM_RTC``'s centre is added after it; a
mirroring transform reverses the winding), and merges them into one mesh: positions, normals,
``COLOR_0`` and the application attributes ``_NAME`` (as ``attributes[NAME]``; vectors as
``NAME_0``, ``NAME_1``...). A file of ``POINTS`` primitives is a point cloud. Sparse accessors
and the integer types of ``KHR_mesh_quantization`` are read. What the data model does not hold
(``TEXCOORD_n``, ``TANGENT``, skins, materials...) is dropped with a warning. Refused in one
line: Draco- or meshopt-compressed data, line primitives, an unknown required extension,
missing or short buffers, accessors that run past their data, indices out of range, a node
hierarchy that is not a tree; a ``.gltf``'s buffers are ``data:`` URIs or files inside its
folder (a URI leading elsewhere is refused).

Writing gives one node, one mesh and one primitive (``TRIANGLES``, or ``POINTS`` for a cloud)
in one buffer (the GLB's BIN chunk; a ``.gltf`` embeds it as a base64 ``data:`` URI, so the file
stands alone and is written atomically). glTF positions are float32: they are stored relative
to a float64 node ``translation`` (the bounding box's centre; none when the coordinates are
float32 values, which are then stored exactly), and the write is refused unless every
coordinate read back (float32 offset + translation, in float64) is within ``tol.precision``
(1e-6) of the bounding-box diagonal of the original. Normals are stored as unit float32
vectors (a zero or non-finite normal is refused), colours as ``COLOR_0`` (uint8 and uint16
normalised, or floats in 0..1), indices as uint16 when they fit, else uint32. Other vertex
attributes are ``_NAME`` accessors holding their values exactly: 8- and 16-bit integers and
finite float32 as themselves; other types as float32 when every value is a float32 value;
otherwise their bytes as 16-bit unsigned vectors. The accessor's ``extras.recon.dtype`` names
the original type, which recon reads back. Face attributes are accessors named in the
primitive's ``extras.recon.face_attributes``; the history, ``obj_info`` lines (LAS header, a
cloud's sensors) and the coordinate type are in ``asset.extras.recon``.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh
from recon_cli.io import text
from recon_cli.io._gltf_parse import BIN_CHUNK, GLB_MAGIC, JSON_CHUNK, Document

_POINTS, _TRIANGLES, _STRIP, _FAN = 0, 4, 5, 6
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_CODES = {"i1": 5120, "u1": 5121, "i2": 5122, "u2": 5123, "u4": 5125, "f4": 5126}
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4"}
# the types accessor extras may name as a value's original type
_RESTORABLE = {"|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f2", "<f4", "<f8"}
# standard semantics the data model has no place for
_NOT_KEPT = ("TEXCOORD_", "TANGENT", "JOINTS_", "WEIGHTS_", "COLOR_")
# required extensions that touch no geometry (materials, textures, lights): read without them
_HARMLESS = ("KHR_materials_", "KHR_texture_", "EXT_texture_", "KHR_lights_")
_HANDLED = ("KHR_mesh_quantization", "CESIUM_RTC")
_COMPRESSED = {
    "KHR_draco_mesh_compression": "Draco",
    "EXT_meshopt_compression": "meshopt",
    "KHR_meshopt_compression": "meshopt",
}
# normalised integers -> the divisor that maps them to 0..1 or -1..1
_NORM = {"i1": 127.0, "u1": 255.0, "i2": 32767.0, "u2": 65535.0, "u4": 4294967295.0}


# --------------------------------------------------------------------------- reading


def decode_gltf(data, where: str) -> tuple[PointCloud | TriangleMesh, dict]:
    """Decode the bytes of a ``.glb`` or ``.gltf`` file: ``(mesh or cloud, details)``.

    Raises
    ------
    InputError
        Malformed, truncated or unsupported content (one line naming ``where``).
    """
    buf = text.as_uint8(data)
    if len(buf) == 0:
        raise InputError("empty file", where)
    doc = Document(buf, where)
    _check_extensions(doc)
    dropped: set[str] = set()
    parts = []
    placed = _mesh_nodes(doc)
    for label, mesh_index, matrix, weights in placed:
        mesh = doc.item("meshes", mesh_index, f"{label}.mesh")
        prims = mesh.get("primitives")
        if not isinstance(prims, list) or not prims or not all(isinstance(p, dict) for p in prims):
            raise doc.fail(f"meshes[{mesh_index}].primitives must be a non-empty array of objects")
        if weights is None and "weights" in mesh:
            weights = mesh["weights"]
        for k, prim in enumerate(prims):
            at = f"meshes[{mesh_index}].primitives[{k}]"
            parts.append(_read_primitive(doc, prim, at, label, matrix, weights, dropped))
    if not parts:
        raise doc.fail("no mesh primitives in the scene: nothing to read")
    obj = _assemble(doc, parts, dropped)
    if dropped:
        text.warn(f"{where}: not kept: {', '.join(sorted(dropped))}")
    asset = doc.json["asset"]
    details: dict[str, Any] = {
        "format": "gltf",
        "container": "GLB" if doc.binary else "JSON",
        "generator": str(asset.get("generator", ""))[:200],
        "mesh_nodes": len(placed),
        "primitives": len(parts),
    }
    shift = _first_translation(placed)
    if shift is not None:
        details["translation"] = shift
    if dropped:
        details["not_kept"] = sorted(dropped)
    return obj, details


def _first_translation(placed: list) -> list[float] | None:
    for _, _, m, _ in placed:
        if m is not None:
            return [float(x) for x in m[:3, 3]]
    return None


def _check_extensions(doc: Document) -> None:
    for name in doc.extensions_required():
        if name in _COMPRESSED:
            raise doc.fail(
                f"requires {name}: recon does not decode {_COMPRESSED[name]} compression"
            )
        if name not in _HANDLED and not name.startswith(_HARMLESS):
            raise doc.fail(f"requires extension {name[:60]!r}, which recon does not read")


def _mesh_nodes(doc: Document) -> list[tuple[str, Any, np.ndarray | None, Any]]:
    """``(label, mesh index, world matrix or None (identity), node weights)`` of each mesh node."""
    nodes = doc.items("nodes")
    meshes = doc.items("meshes")
    if doc.items("scenes"):
        scene = doc.item("scenes", doc.json.get("scene", 0), "scene")
        roots = scene.get("nodes", [])
        where = "scene.nodes"
    elif nodes:
        children = set()
        for node in nodes:
            kids = node.get("children", [])
            children |= {c for c in kids if type(c) is int} if isinstance(kids, list) else set()
        roots = [i for i in range(len(nodes)) if i not in children]
        where = "nodes"
    else:  # meshes and no nodes: each mesh where it stands
        return [(f"meshes[{i}]", i, None, None) for i in range(len(meshes))]
    if not isinstance(roots, list):
        raise doc.fail(f"{where} must be an array of node indices")
    rtc = _rtc_centre(doc)
    out: list[tuple[str, Any, np.ndarray | None, Any]] = []
    seen: set[int] = set()
    stack: list[tuple[Any, np.ndarray | None, str]] = [(r, rtc, where) for r in reversed(roots)]
    while stack:
        i, parent, at = stack.pop()
        node = doc.item("nodes", i, at)
        if i in seen:
            raise doc.fail(f"nodes[{i}] is reached twice: the node hierarchy must be a tree")
        seen.add(i)
        local = _local_matrix(doc, node, f"nodes[{i}]")
        world = local if parent is None else (parent if local is None else parent @ local)
        ext = node.get("extensions")
        if isinstance(ext, dict) and "EXT_mesh_gpu_instancing" in ext:
            raise doc.fail(f"nodes[{i}] is instanced (EXT_mesh_gpu_instancing): not read")
        if "mesh" in node:
            out.append((f"nodes[{i}]", node["mesh"], world, node.get("weights")))
        kids = node.get("children", [])
        if not isinstance(kids, list):
            raise doc.fail(f"nodes[{i}].children must be an array of node indices")
        stack += [(c, world, f"nodes[{i}].children") for c in reversed(kids)]
    return out


def _rtc_centre(doc: Document) -> np.ndarray | None:
    """The translation ``CESIUM_RTC`` adds to the whole scene, or None."""
    ext = doc.json.get("extensions")
    if not isinstance(ext, dict) or "CESIUM_RTC" not in ext:
        return None
    rtc = ext["CESIUM_RTC"]
    centre = doc.numbers(rtc.get("center") if isinstance(rtc, dict) else None, 3, "CESIUM_RTC")
    m = np.eye(4)
    m[:3, 3] = centre
    return m


def _local_matrix(doc: Document, node: dict, at: str) -> np.ndarray | None:
    """The node's 4x4 local transform (float64), None when it has none."""
    if "matrix" in node:
        m = doc.numbers(node["matrix"], 16, f"{at}.matrix").reshape(4, 4).T  # column-major
        if not np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise doc.fail(f"{at}.matrix is not affine (its last row is not 0 0 0 1)")
        return None if np.array_equal(m, np.eye(4)) else m
    if not {"translation", "rotation", "scale"} & set(node):
        return None
    m = np.eye(4)
    if "scale" in node:
        m[:3, :3] = np.diag(doc.numbers(node["scale"], 3, f"{at}.scale"))
    if "rotation" in node:
        x, y, z, w = doc.numbers(node["rotation"], 4, f"{at}.rotation")
        norm = float(np.sqrt(x * x + y * y + z * z + w * w))
        if norm == 0:
            raise doc.fail(f"{at}.rotation is the zero quaternion")
        x, y, z, w = x / norm, y / norm, z / norm, w / norm
        rot = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        m[:3, :3] = rot @ m[:3, :3]
    if "translation" in node:
        m[:3, 3] = doc.numbers(node["translation"], 3, f"{at}.translation")
    return None if np.array_equal(m, np.eye(4)) else m


class _Part(dict):
    """One primitive's arrays: ``key`` (shared vertices), ``positions``, ``faces`` or None, ..."""


def _read_primitive(
    doc: Document,
    prim: dict,
    at: str,
    label: str,
    matrix: np.ndarray | None,
    weights: Any,
    dropped: set[str],
) -> _Part:
    mode = doc.integer(prim, "mode", at, default=_TRIANGLES)
    if mode in (1, 2, 3):
        raise doc.fail(f"{at} holds lines (mode {mode}): recon reads triangles and points")
    if mode not in (_POINTS, _TRIANGLES, _STRIP, _FAN):
        raise doc.fail(f"{at}.mode {mode} is not a glTF primitive mode")
    attrs = prim.get("attributes")
    if not isinstance(attrs, dict) or "POSITION" not in attrs:
        raise doc.fail(f"{at} has no POSITION attribute")
    ext = prim.get("extensions")
    if isinstance(ext, dict) and "KHR_draco_mesh_compression" in ext:
        acc = doc.item("accessors", attrs["POSITION"], f"{at}.attributes.POSITION")
        if "bufferView" not in acc:  # no uncompressed fallback beside the Draco data
            raise doc.fail(f"{at} is Draco-compressed: recon does not decode Draco")
    pos = _vectors(doc, attrs["POSITION"], f"{at}.attributes.POSITION", 3)
    n = len(pos)
    part = _Part(positions=pos, normals=None, colors=None, attributes={}, face_attributes={})
    part["key"] = (label, tuple(sorted((str(k), str(v)) for k, v in attrs.items())))
    for sem, index in attrs.items():
        where = f"{at}.attributes.{sem}"
        if sem == "POSITION":
            continue
        if sem == "NORMAL":
            part["normals"] = _vectors(doc, index, where, 3, n)
        elif sem == "COLOR_0":
            part["colors"] = _colors(doc, index, where, n)
        elif sem.startswith("_") and len(sem) > 1:
            part["attributes"].update(_custom(doc, index, where, sem[1:], n))
        else:
            dropped.add(sem if sem.startswith(_NOT_KEPT) else f"attribute {sem[:40]!r}")
    _morph(doc, prim, at, part, weights)
    if mode == _POINTS:
        part["faces"] = None
    else:
        part["faces"] = _faces(doc, prim, at, mode, n)
        part["face_attributes"] = _face_attributes(doc, prim, at, len(part["faces"]))
    if matrix is not None:
        _transform(doc, part, matrix, label)
    return part


def _vectors(doc: Document, index: Any, at: str, width: int, count: int | None = None):
    """A float accessor of ``width`` columns (normalised or plain integers converted)."""
    arr, acc = doc.accessor(index, at)
    if arr.shape[1] != width or (count is not None and len(arr) != count):
        raise doc.fail(
            f"{at}: expected {count or 'some'} VEC{width} elements, got {len(arr)} of "
            f"{arr.shape[1]} components"
        )
    if arr.dtype == np.float32:
        if not np.isfinite(arr).all():
            raise doc.fail(f"{at} holds a NaN or infinite value")
        return arr
    values = arr.astype(np.float32)
    if acc.get("normalized") is True:
        values /= np.float32(_NORM[arr.dtype.str[1:]])
        np.maximum(values, -1.0, out=values)
    return values


def _colors(doc: Document, index: Any, at: str, n: int) -> np.ndarray:
    arr, acc = doc.accessor(index, at)
    values = _restore(doc, arr, acc, at)
    if values.ndim != 2 or values.shape[1] not in (3, 4) or len(values) != n:
        raise doc.fail(f"{at}: expected {n} VEC3 or VEC4 colours")
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        raise doc.fail(f"{at} holds a NaN or infinite value")
    return values


def _custom(doc: Document, index: Any, at: str, name: str, n: int) -> dict[str, np.ndarray]:
    arr, acc = doc.accessor(index, at)
    if len(arr) != n:
        raise doc.fail(f"{at}: {len(arr)} elements for {n} vertices")
    values = _restore(doc, arr, acc, at)
    if values.ndim == 1:
        return {name: values}
    if acc.get("normalized") is True and values.dtype.kind in "iu":
        values = np.maximum(values / np.float32(_NORM[values.dtype.str[1:]]), -1).astype(np.float32)
    return {f"{name}_{k}": np.array(values[:, k]) for k in range(values.shape[1])}


def _restore(doc: Document, arr: np.ndarray, acc: dict, at: str) -> np.ndarray:
    """An accessor's values in the type ``extras.recon.dtype`` names (as stored without one).

    ``(count,)`` for a scalar or a restored value, else ``(count, width)``.
    """
    extras = acc.get("extras")
    ours = extras.get("recon") if isinstance(extras, dict) else None
    if not isinstance(ours, dict) or "dtype" not in ours:
        return np.array(arr[:, 0]) if arr.shape[1] == 1 else np.array(arr)
    dt = ours["dtype"]
    if not isinstance(dt, str) or dt not in _RESTORABLE:
        raise doc.fail(f"{at}: extras.recon.dtype {str(dt)[:20]!r} is not a type recon writes")
    dtype = np.dtype(dt)
    if ours.get("encoding") == "bits":
        if arr.dtype != np.uint16 or 2 * arr.shape[1] != dtype.itemsize:
            raise doc.fail(f"{at}: {dt} bits need {dtype.itemsize // 2} unsigned shorts")
        return np.ascontiguousarray(arr).view(dtype).reshape(-1).astype(dtype.newbyteorder("="))
    width = arr.shape[1]
    with np.errstate(invalid="ignore", over="ignore"):
        values = arr.astype(dtype.newbyteorder("="))
        if not np.array_equal(values.astype(arr.dtype), arr):
            raise doc.fail(f"{at}: values that type {dt} (extras.recon.dtype) does not hold")
    return values[:, 0] if width == 1 else values


def _faces(doc: Document, prim: dict, at: str, mode: int, n: int) -> np.ndarray:
    """Triangles (m, 3) int64 from the indices (or the vertex order) of a triangle primitive."""
    if "indices" in prim:
        arr, _ = doc.accessor(prim["indices"], f"{at}.indices")
        if arr.shape[1] != 1 or arr.dtype.kind != "u" or arr.dtype.itemsize == 8:
            raise doc.fail(f"{at}.indices must be scalar unsigned bytes, shorts or ints")
        idx = arr[:, 0].astype(np.int64)
        if idx.max() >= n:
            raise doc.fail(f"{at}.indices: index {int(idx.max())} out of range for {n} vertices")
    else:
        idx = np.arange(n, dtype=np.int64)
    k = len(idx)
    if mode == _TRIANGLES:
        if k % 3:
            raise doc.fail(f"{at}: {k} indices do not make whole triangles")
        return idx.reshape(-1, 3)
    if k < 3:
        raise doc.fail(f"{at}: a triangle {'strip' if mode == _STRIP else 'fan'} of {k} vertices")
    i = np.arange(k - 2)
    if mode == _STRIP:  # every second triangle is wound the other way
        odd = i % 2
        return np.column_stack([idx[i + odd], idx[i + 1 - odd], idx[i + 2]])
    return np.column_stack([idx[i + 1], idx[i + 2], np.full(k - 2, idx[0])])


def _face_attributes(doc: Document, prim: dict, at: str, m: int) -> dict[str, np.ndarray]:
    extras = prim.get("extras")
    ours = extras.get("recon") if isinstance(extras, dict) else None
    named = ours.get("face_attributes") if isinstance(ours, dict) else None
    if named is None:
        return {}
    if not isinstance(named, dict):
        raise doc.fail(f"{at}.extras.recon.face_attributes must be an object")
    out = {}
    for name, index in named.items():
        where = f"{at}.extras.recon.face_attributes.{name}"
        arr, acc = doc.accessor(index, where)
        values = _restore(doc, arr, acc, where)
        if values.shape != (m,):
            raise doc.fail(f"{where}: expected {m} scalars, one per triangle")
        out[name] = values
    return out


def _morph(doc: Document, prim: dict, at: str, part: _Part, weights: Any) -> None:
    """Add the morph targets' displacements at their default weights (nothing when all are 0)."""
    targets = prim.get("targets")
    if targets is None:
        return
    if not isinstance(targets, list) or not all(isinstance(t, dict) for t in targets):
        raise doc.fail(f"{at}.targets must be an array of objects")
    w = doc.numbers(weights if weights is not None else [0] * len(targets), len(targets), at)
    n = len(part["positions"])
    for k, target in enumerate(targets):
        if w[k] == 0:
            continue
        for sem in ("POSITION", "NORMAL"):
            if sem in target and (sem == "POSITION" or part["normals"] is not None):
                d = _vectors(doc, target[sem], f"{at}.targets[{k}].{sem}", 3, n)
                key = "positions" if sem == "POSITION" else "normals"
                part[key] = np.asarray(part[key], np.float64) + w[k] * d
    if part["normals"] is not None and np.any(w):
        part["normals"] = _unit(part["normals"])


def _unit(v: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v, dtype=np.float64), where=length > 0)


def _transform(doc: Document, part: _Part, matrix: np.ndarray, label: str) -> None:
    """Apply a node's world matrix to the part's positions and normals (float64)."""
    lin, shift = matrix[:3, :3], matrix[:3, 3]
    pos = np.asarray(part["positions"], np.float64)
    with np.errstate(all="ignore"):  # huge matrices: checked below
        if np.array_equal(lin, np.eye(3)):
            pos = pos + shift  # a translation: the float32 offsets plus it, exactly
        else:
            det = float(np.linalg.det(lin))
            if not np.isfinite(det) or abs(det) < 1e-300:
                raise doc.fail(f"{label}'s transform is singular: its mesh would collapse")
            pos = pos @ lin.T + shift
            if part["normals"] is not None:
                n = np.asarray(part["normals"], np.float64) @ np.linalg.inv(lin)
                part["normals"] = _unit(n)
            if det < 0 and part["faces"] is not None:  # a mirror turns the triangles over
                part["faces"] = part["faces"][:, [0, 2, 1]]
    if not np.isfinite(pos).all():
        raise doc.fail(f"{label}'s transform takes coordinates past the float64 range")
    part["positions"] = pos


def _assemble(doc: Document, parts: list[_Part], dropped: set[str]) -> PointCloud | TriangleMesh:
    """One mesh (or cloud) of the primitives; vertices shared by primitives are not repeated."""
    points = [p["faces"] is None for p in parts]
    if any(points) and not all(points):
        raise doc.fail("the file mixes point and triangle primitives: recon reads one kind")
    first: dict[Any, int] = {}
    unique: list[_Part] = []
    for p in parts:
        if p["key"] not in first:
            first[p["key"]] = len(unique)
            unique.append(p)
    starts = np.cumsum([0] + [len(p["positions"]) for p in unique])
    pos = _concat([p["positions"] for p in unique])
    normals = _common(unique, "normals", "NORMAL", dropped)
    colors = _merged_colors(unique, dropped)
    attributes = _common_dict(unique, "attributes", dropped)
    extras = doc.json["asset"].get("extras")
    ours = extras.get("recon") if isinstance(extras, dict) else None
    ours = ours if isinstance(ours, dict) else {}
    history = _lines(ours.get("history"))
    obj_info = _lines(ours.get("obj_info"))
    dtype = np.float64 if ours.get("point_dtype") == "float64" else pos.dtype
    pos = pos.astype(dtype, copy=False)  # double in, double out
    common: dict[str, Any] = dict(
        normals=normals,
        colors=colors,
        attributes=attributes,
        history=history,
        obj_info=obj_info,
        point_dtype=dtype,
    )
    if all(points):
        return PointCloud(points=pos, **common)
    faces = _concat(
        [p["faces"] + starts[first[p["key"]]] if k else p["faces"] for k, p in enumerate(parts)]
    )
    face_attributes = _common_dict(parts, "face_attributes", dropped)
    return TriangleMesh(vertices=pos, faces=faces, face_attributes=face_attributes, **common)


def _lines(v: Any) -> list[str]:
    return [str(x) for x in v] if isinstance(v, list) else []


def _concat(arrays: list[np.ndarray]) -> np.ndarray:
    if len(arrays) == 1:
        return arrays[0]
    return np.concatenate([np.asarray(a) for a in arrays])


def _common(parts: list[_Part], key: str, label: str, dropped: set[str]) -> np.ndarray | None:
    have = [p[key] is not None for p in parts]
    if not any(have):
        return None
    if not all(have):
        dropped.add(f"{label} (on {sum(have)} of {len(parts)} primitives)")
        return None
    return _concat([p[key] for p in parts])


def _merged_colors(parts: list[_Part], dropped: set[str]) -> np.ndarray | None:
    colors = _common(parts, "colors", "COLOR_0", dropped)
    if colors is None or len({(p["colors"].dtype, p["colors"].shape[1]) for p in parts}) == 1:
        return colors
    # primitives of different colour types: RGBA floats in 0..1
    out = []
    for p in parts:
        c = p["colors"]
        f = c / np.float32(_NORM[c.dtype.str[1:]]) if c.dtype.kind == "u" else c.astype(np.float32)
        if f.shape[1] == 3:
            f = np.column_stack([f, np.ones(len(f), np.float32)])
        out.append(f.astype(np.float32))
    return np.concatenate(out)


def _common_dict(parts: list[_Part], key: str, dropped: set[str]) -> dict[str, np.ndarray]:
    names = [set(p[key]) for p in parts]
    everywhere = set.intersection(*names)
    for name in sorted(set.union(*names) - everywhere):
        dropped.add(f"{key[:-1].replace('_', ' ')} {name!r} (not on every primitive)")
    return {name: _concat([p[key][name] for p in parts]) for name in sorted(everywhere)}


def read_gltf(path: str | os.PathLike, data=None) -> PointCloud | TriangleMesh:
    """Read a ``.glb`` or ``.gltf`` file (``-``: standard input) as a mesh or a cloud."""
    from recon_cli.io.ply import read_bytes

    return decode_gltf(read_bytes(path) if data is None else data, text.where_of(path))[0]


# --------------------------------------------------------------------------- writing


class _Buffer:
    """The binary buffer being laid out: bufferViews and accessors over pieces of bytes."""

    def __init__(self) -> None:
        self.pieces: list[np.ndarray] = []
        self.views: list[dict] = []
        self.accessors: list[dict] = []
        self.size = 0

    def view(self, data: np.ndarray, stride: int | None = None, target: int | None = None) -> int:
        raw = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        bv: dict[str, Any] = {"buffer": 0, "byteOffset": self.size, "byteLength": len(raw)}
        if stride is not None:
            bv["byteStride"] = stride
        if target is not None:
            bv["target"] = target
        self.views.append(bv)
        self.pieces.append(raw)
        self.size += len(raw)
        if self.size % 4:
            pad = 4 - self.size % 4
            self.pieces.append(np.zeros(pad, np.uint8))
            self.size += pad
        return len(self.views) - 1

    def accessor(self, enc: dict, count: int, vertex: bool, target: int | None = None) -> int:
        """An accessor over a new bufferView of ``enc`` (see :func:`_encode`).

        ``vertex``: a vertex attribute (elements on 4-byte boundaries, target ARRAY_BUFFER).
        """
        data, width = enc["data"], enc["width"]
        elem = width * data.dtype.itemsize
        stride = None
        if vertex and elem % 4:  # vertex attribute elements start on 4-byte boundaries
            stride = elem + 4 - elem % 4
            rows = np.zeros((count, stride), np.uint8)
            rows[:, :elem] = np.ascontiguousarray(data).view(np.uint8).reshape(count, elem)
            data = rows
        view = self.view(data, stride, _ARRAY_BUFFER if vertex else target)
        acc: dict[str, Any] = {
            "bufferView": view,
            "componentType": _CODES[enc["data"].dtype.str[1:]],
            "count": count,
            "type": _TYPES[width],
        }
        for key in ("normalized", "min", "max", "extras"):
            if enc.get(key) is not None:
                acc[key] = enc[key]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _fail(where: str, message: str) -> ParameterError:
    return ParameterError(f"{where}: {message}" if where else message)


def _encode(values: np.ndarray, name: str, where: str) -> dict:
    """How a per-vertex (or per-face) scalar array is stored exactly (data, width, extras)."""
    a = np.asarray(values)
    if a.ndim != 1:
        raise _fail(where, f"attribute {name!r} has shape {a.shape}: glTF attributes are 1-d here")
    dt = a.dtype
    if dt.kind not in "biuf":
        raise _fail(where, f"attribute {name!r} of type {dt} cannot be written to glTF")
    if dt.str[1:] in ("u1", "i1", "u2", "i2") or (dt == np.float32 and np.isfinite(a).all()):
        return {"data": a.astype(dt.newbyteorder("<")), "width": 1}
    tag = {"recon": {"dtype": dt.newbyteorder("<").str if dt.itemsize > 1 else dt.str}}
    if dt.kind == "b":
        return {"data": a.astype(np.uint8), "width": 1, "extras": tag}
    if dt.kind in "iu":
        fits = len(a) == 0 or (int(a.min()) >= -(2**24) and int(a.max()) <= 2**24)
        if fits:
            return {"data": a.astype(np.float32), "width": 1, "extras": tag}
    else:
        with np.errstate(over="ignore", invalid="ignore"):
            f = a.astype(np.float32)
            if np.isfinite(f).all() and np.array_equal(f.astype(dt), a):
                return {"data": f, "width": 1, "extras": tag}
    # the value's bytes as unsigned shorts, read back bit for bit
    bits = np.ascontiguousarray(a.astype(dt.newbyteorder("<"))).view("<u2")
    tag["recon"]["encoding"] = "bits"
    return {"data": bits.reshape(len(a), -1), "width": dt.itemsize // 2, "extras": tag}


def _encode_colors(c: np.ndarray, where: str) -> dict:
    if c.ndim != 2 or c.shape[1] not in (3, 4):
        raise _fail(where, f"colours of shape {c.shape}: glTF COLOR_0 holds RGB or RGBA")
    width = c.shape[1]
    dt = c.dtype
    if dt == np.uint8 or dt == np.uint16:
        return {"data": c.astype(dt.newbyteorder("<")), "width": width, "normalized": True}
    tag = {"recon": {"dtype": dt.newbyteorder("<").str if dt.itemsize > 1 else dt.str}}
    if dt.kind == "f":
        with np.errstate(over="ignore", invalid="ignore"):
            f = c.astype(np.float32)
            exact = np.array_equal(f.astype(dt), c)
        if not (np.isfinite(f).all() and f.min() >= 0 and f.max() <= 1 and exact):
            raise _fail(
                where,
                "float colours must be float32 values in 0..1 for glTF COLOR_0 (these are not)",
            )
        return {"data": f, "width": width, "extras": tag if dt != np.float32 else None}
    if dt.kind in "biu" and len(c):
        lo, hi = int(c.min()), int(c.max())
        for target in (np.uint8, np.uint16):
            if lo >= 0 and hi <= np.iinfo(target).max:
                return {"data": c.astype(target), "width": width, "normalized": True, "extras": tag}
    raise _fail(where, f"colours of type {dt} with values outside 0..65535 do not fit glTF COLOR_0")


def _positions(
    obj: PointCloud | TriangleMesh, where: str, origin: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(float32 positions, float64 translation, their column min, max)``.

    Raises ParameterError when a coordinate read back (offset + translation) would be further
    than ``tol.precision`` of the bounding-box diagonal from the original.
    """
    from recon_cli.io import _gltf_kernel as K
    from recon_cli.tolerances import tol

    v = np.ascontiguousarray(obj.vertices)  # one kernel signature per float type
    lo, hi = np.empty(3), np.empty(3)
    bad = K.bounds(v, lo, hi)
    if bad >= 0:
        raise _fail(where, f"vertex {bad} has a NaN or infinite coordinate")
    if origin is None and (v.dtype == np.float32 or K.all_float32(v)):
        # float32 values are stored as they are: no translation, nothing rounded
        return v.astype(np.float32, copy=False), np.zeros(3), lo, hi
    if origin is None:
        origin = 0.5 * (lo + hi)
    origin = np.asarray(origin, np.float64)
    p32 = np.empty(v.shape, np.float32)
    lo32, hi32 = np.empty(3, np.float32), np.empty(3, np.float32)
    err = K.float32_offsets(v.astype(np.float64, copy=False), origin, p32, lo32, hi32)
    bound = tol.precision * float(np.linalg.norm(hi - lo))
    if not err <= bound:
        raise _fail(
            where,
            f"glTF stores float32 positions: relative to the translation "
            f"({', '.join(f'{x:.17g}' for x in origin)}) they would move by up to {err:.3g}, "
            f"more than {tol.precision:g} of the bounding-box diagonal ({bound:.3g})",
        )
    return p32, origin, lo32, hi32


def _unit_normals(obj: PointCloud | TriangleMesh, where: str) -> np.ndarray:
    from recon_cli.io import _gltf_kernel as K

    n = np.ascontiguousarray(obj.normals)
    out = np.empty(n.shape, np.float32)
    bad, worst = K.unit_vectors(n, out)
    if bad >= 0:
        raise _fail(
            where,
            f"normal of vertex {bad} is zero or not finite: glTF NORMAL holds unit vectors",
        )
    if worst > 1e-3:
        text.warn(f"{where}: normals scaled to unit length (glTF NORMAL holds unit vectors)")
    return out


def gltf_document(
    obj: PointCloud | TriangleMesh,
    where: str = "",
    origin: np.ndarray | None = None,
    up: np.ndarray | None = None,
) -> tuple[dict, list[np.ndarray], int]:
    """The glTF JSON object of ``obj`` and its binary buffer as pieces (``(doc, pieces, size)``).

    Parameters
    ----------
    obj : PointCloud or TriangleMesh
    where : str
        The output's name for messages.
    origin : (3,) float64, optional
        The translation the float32 positions are stored relative to (default: see the
        module docstring).
    up : (3, 3) array, optional
        A rotation whose entries are 0 and +-1 applied after the translation (a node
        ``matrix``): 3D Tiles' content is y-up, so a z-up mesh is turned by it.

    Raises
    ------
    ParameterError
        What glTF cannot hold exactly (see the module docstring), naming ``where``.
    """
    from recon_cli import __version__

    mesh = obj if isinstance(obj, TriangleMesh) else None
    n = len(obj.vertices)
    if n == 0 or (mesh is not None and len(mesh.faces) == 0):
        what = "no vertices" if n == 0 else "no faces"
        raise _fail(where, f"a {'mesh' if mesh else 'cloud'} with {what}: glTF holds none")
    p32, shift, lo, hi = _positions(obj, where, origin)
    buf = _Buffer()
    position = {"data": p32, "width": 3, "min": _floats(lo), "max": _floats(hi)}
    attrs = {"POSITION": buf.accessor(position, n, True)}
    if obj.normals is not None:
        attrs["NORMAL"] = buf.accessor({"data": _unit_normals(obj, where), "width": 3}, n, True)
    if obj.colors is not None:
        attrs["COLOR_0"] = buf.accessor(_encode_colors(np.asarray(obj.colors), where), n, True)
    for name, values in obj.attributes.items():
        attrs["_" + name] = buf.accessor(_encode(values, name, where), n, True)
    prim: dict[str, Any] = {"attributes": attrs, "mode": _POINTS if mesh is None else _TRIANGLES}
    if mesh is not None:
        prim["indices"] = _indices(buf, mesh.faces, n, where)
        faces_named = {
            name: buf.accessor(_encode(v, name, where), len(mesh.faces), False)
            for name, v in mesh.face_attributes.items()
        }
        if faces_named:
            prim["extras"] = {"recon": {"face_attributes": faces_named}}
    node: dict[str, Any] = {"mesh": 0}
    if up is not None:
        rot = np.asarray(up, np.float64)
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = rot @ shift
        node["matrix"] = _floats(m.T.reshape(-1))
    elif shift.any():
        node["translation"] = _floats(shift)
    info = list(obj.obj_info) + [s.to_line() for s in getattr(obj, "sensors", ())]
    ours: dict[str, Any] = {"history": list(obj.history), "obj_info": info}
    if np.dtype(obj.point_dtype) == np.float64:
        ours["point_dtype"] = "float64"
    doc = {
        "asset": {"version": "2.0", "generator": f"recon {__version__}", "extras": {"recon": ours}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"primitives": [prim]}],
        "accessors": buf.accessors,
        "bufferViews": buf.views,
        "buffers": [{"byteLength": buf.size}],
    }
    return doc, buf.pieces, buf.size


def _floats(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(a).reshape(-1)]


def _indices(buf: _Buffer, faces: np.ndarray, n: int, where: str) -> int:
    f = np.asarray(faces)
    if f.size and (int(f.min()) < 0 or int(f.max()) >= n):
        raise _fail(where, f"a face index is out of range for {n} vertices")
    # the largest value of each type is the primitive restart value: not an index
    dtype: np.dtype
    if n <= 0xFFFF:
        dtype = np.dtype("<u2")
    elif n <= 0xFFFFFFFF:
        dtype = np.dtype("<u4")
    else:
        raise _fail(where, f"{n} vertices: glTF indices address at most 4294967295")
    flat = {"data": f.astype(dtype).reshape(-1), "width": 1}
    return buf.accessor(flat, f.size, False, _ELEMENT_ARRAY_BUFFER)


def _json_bytes(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")


def emit_gltf(
    obj: PointCloud | TriangleMesh,
    put: Callable[[bytes | memoryview], Any],
    binary: bool = True,
    where: str = "",
    origin: np.ndarray | None = None,
    up: np.ndarray | None = None,
) -> None:
    """Encode ``obj`` as GLB (or ``.gltf`` JSON, its buffer embedded), piece by piece to ``put``.

    Every check runs before the first piece is put (see :func:`gltf_document`).
    """
    doc, pieces, size = gltf_document(obj, where, origin, up)
    if not binary:
        b64 = base64.b64encode(b"".join(p.tobytes() for p in pieces)).decode("ascii")
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + b64
        put(_json_bytes(doc))
        return
    head = _json_bytes(doc)
    head += b" " * (-len(head) % 4)
    total = 12 + 8 + len(head) + 8 + size
    put(GLB_MAGIC + struct.pack("<II", 2, total) + struct.pack("<II", len(head), JSON_CHUNK) + head)
    put(struct.pack("<II", size, BIN_CHUNK))
    for piece in pieces:
        put(piece.data)


def glb_bytes(obj: PointCloud | TriangleMesh, **kwargs: Any) -> bytes:
    """The GLB encoding of ``obj`` (keyword arguments as :func:`emit_gltf`)."""
    out: list[bytes] = []
    emit_gltf(obj, lambda b: out.append(bytes(b)), **kwargs)
    return b"".join(out)


def write_gltf(
    obj: PointCloud | TriangleMesh, path: str | os.PathLike, binary: bool | None = None
) -> None:
    """Write ``obj`` atomically as ``.glb`` (binary) or ``.gltf`` (``-``: standard output).

    ``binary`` None: by the suffix (``.gltf`` is JSON, anything else GLB).
    """
    from recon_cli.io.atomic import write_pieces

    where = text.where_of(path)
    if binary is None:
        binary = not str(path).lower().endswith(".gltf")
    chunks: list[Any] = []  # encoded (and so checked) before the output is opened
    emit_gltf(obj, chunks.append, binary=binary, where=where)

    def produce(put: Callable[[bytes | memoryview], None]) -> None:
        for c in chunks:
            put(c)

    write_pieces(path, produce)

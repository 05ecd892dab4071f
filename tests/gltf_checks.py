"""The Khronos glTF-Validator on files the tests write (``make js`` installs it in tools/gltf)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
TOOLS = ROOT / "tools" / "gltf"


def node_tool(script: str, *args: str, timeout: float = 300) -> str:
    """Run ``tools/gltf/<script>`` with node; its stdout (the test fails when it cannot run)."""
    node = shutil.which("node")
    if node is None or not (TOOLS / "node_modules").is_dir():
        pytest.fail("the glTF checkers are not installed: run `make js` (needs node and npm)")
    r = subprocess.run(
        [node, str(TOOLS / script), *args], capture_output=True, text=True, timeout=timeout
    )
    assert r.returncode == 0, r.stderr
    return r.stdout


def validate(*paths) -> list[dict]:
    """The glTF-Validator's report of each file: ``file``, ``errors``, ``warnings``, ``messages``.

    One node process for all of them.
    """
    return json.loads(node_tool("validate.mjs", *map(str, paths)))


def assert_valid(*paths) -> None:
    """Every file passes the glTF-Validator with 0 errors and 0 warnings."""
    for rep in validate(*paths):
        assert rep["errors"] == 0 and rep["warnings"] == 0, rep


def glb_split(glb: bytes) -> tuple[dict, bytes]:
    """A GLB's JSON object and what follows its JSON chunk (the BIN chunk with its header)."""
    n = struct.unpack_from("<I", glb, 12)[0]
    return json.loads(glb[20 : 20 + n]), glb[20 + n :]


def glb_join(doc: dict, tail: bytes) -> bytes:
    """The GLB of ``doc`` followed by ``tail`` (as :func:`glb_split` gives it)."""
    head = json.dumps(doc).encode()
    head += b" " * (-len(head) % 4)
    size = struct.pack("<III", 2, 20 + len(head) + len(tail), len(head))
    return b"glTF" + size + b"JSON" + head + tail


class Builder:
    """A glTF of hand-made accessors, in one buffer (for layouts our writer does not make)."""

    def __init__(self) -> None:
        self.bin = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def accessor(self, arr, kind: str, ctype: int, stride: int | None = None, **extra) -> int:
        """A new bufferView holding ``arr`` and an accessor over it; the accessor's index."""
        arr = np.ascontiguousarray(arr)
        self.bin += b"\0" * (-len(self.bin) % 4)
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": arr.nbytes}
        if stride:
            view["byteStride"] = stride
        self.bin += arr.tobytes()
        self.views.append(view)
        n = len(arr)
        self.accessors.append(
            {"bufferView": len(self.views) - 1, "componentType": ctype, "count": n, "type": kind}
            | extra
        )
        return len(self.accessors) - 1

    def sparse(self, acc: int, indices, values) -> None:
        """Give accessor ``acc`` sparse substitutions: ``values`` at ``indices`` (uint8)."""
        idx = self.accessor(np.asarray(indices, np.uint8), "SCALAR", 5121)
        val = self.accessor(
            values, self.accessors[acc]["type"], self.accessors[acc]["componentType"]
        )
        self.accessors[acc]["sparse"] = {
            "count": len(indices),
            "indices": {"bufferView": self.accessors[idx]["bufferView"], "componentType": 5121},
            "values": {"bufferView": self.accessors[val]["bufferView"]},
        }

    def doc(self, meshes: list, nodes: list | None = None, **top) -> dict:
        """The glTF object of ``meshes`` (one node each unless ``nodes``), ``top`` keys added."""
        nodes = nodes if nodes is not None else [{"mesh": i} for i in range(len(meshes))]
        roots = [i for i in range(len(nodes)) if not any(i in n.get("children", []) for n in nodes)]
        return {
            "asset": {"version": "2.0", "generator": "test builder"},
            "scene": 0,
            "scenes": [{"nodes": roots}],
            "nodes": nodes,
            "meshes": meshes,
            "accessors": self.accessors,
            "bufferViews": self.views,
            "buffers": [{"byteLength": len(self.bin)}],
        } | top

    def glb(self, doc: dict) -> bytes:
        """The GLB of ``doc`` (from :meth:`doc`) with the buffer as its BIN chunk."""
        body = bytes(self.bin) + b"\0" * (-len(self.bin) % 4)
        return glb_join(doc, struct.pack("<I", len(body)) + b"BIN\0" + body)

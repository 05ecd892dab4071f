"""The fitted field of :mod:`recon_cli.stages.learned`: the network and its file.

The network comes with its map from world coordinates; the file holds weights and
description in one ``.npz`` (no pickle).

PyTorch is imported through :func:`compute` only when a field is fitted or queried.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from typing import Any

import numpy as np

from recon_cli.errors import BackendError, InputError, ParameterError

FIELDS = ("sdf", "occupancy")
INSTALL_HINT = "fit-sdf needs PyTorch: pip install recon[learned]"
FORMAT = "recon-fit-sdf-1"
RADIUS = 0.5  # radius of the initial sphere, network coordinates
OCC_GAIN = 10.0  # occupancy: p(inside) = sigmoid(-gain * s), so the sphere init is a valid field


def compute():
    """The compute module, importing torch; a one-line error when the extra is missing."""
    os.environ.setdefault(
        "OMP_WAIT_POLICY", "PASSIVE"
    )  # busy-waiting threads crawl on a shared CPU
    try:
        from recon_cli.stages.learned import _torch_net
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] == "torch":
            raise BackendError(INSTALL_HINT) from None
        raise
    return _torch_net


def field_name(v: Any) -> str:
    """``v`` as one of :data:`FIELDS`, else a :class:`ParameterError`."""
    f = str(v).lower()
    if f not in FIELDS:
        raise ParameterError(f"field must be one of {', '.join(FIELDS)}, got {v!r}")
    return f


@dataclass
class SdfModel:
    """A fitted field: the network and the map from world to network coordinates.

    Attributes
    ----------
    net : torch module
        s(q) on network coordinates ``q = (x - center) / scale``.
    center : (3,) float64
    scale : float
        World units per network unit; signed distances are ``scale * s``.
    field : {"sdf", "occupancy"}
    config : dict
        ``width``, ``depth``, ``frequencies``.
    """

    net: Any
    center: np.ndarray
    scale: float
    field: str
    config: dict = dataclass_field(default_factory=dict)

    def _q(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        return ((x - self.center) / self.scale).astype(np.float32)

    def values(self, points: np.ndarray) -> np.ndarray:
        """Field at (k, 3) world points.

        Signed distance (world units, negative inside) for ``sdf``, ``0.5 - p(inside)`` for
        ``occupancy`` (negative inside, zero at p = 1/2).
        """
        raw = compute().values(self.net, self._q(points))
        return self._to_field(raw)

    def gradients(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Field (as :meth:`values`) and its gradient in world units (autodiff), (k,) and (k, 3)."""
        raw, g = compute().gradients(self.net, self._q(points))
        val = self._to_field(raw)
        if self.field == "sdf":
            return val, g.astype(np.float64)
        p = 1.0 / (1.0 + np.exp(OCC_GAIN * raw.astype(np.float64)))  # p(inside)
        return val, (OCC_GAIN * p * (1 - p))[:, None] * g / self.scale

    def _to_field(self, raw: np.ndarray) -> np.ndarray:
        raw = raw.astype(np.float64)
        if self.field == "sdf":
            return raw * self.scale
        return 0.5 - 1.0 / (1.0 + np.exp(OCC_GAIN * raw))


def save_model(model: SdfModel, path: str | os.PathLike) -> None:
    """Write the fitted weights and the coordinate map as ``.npz`` (atomically; no pickle)."""
    from recon_cli.io.atomic import write_bytes
    from recon_cli.io.npz import npz_bytes

    arrays = {f"param:{k}": v for k, v in compute().state_arrays(model.net).items()}
    meta = {
        "format": FORMAT,
        "field": model.field,
        "scale": model.scale,
        "center": list(map(float, model.center)),
        **model.config,
    }
    write_bytes(path, npz_bytes({"meta": np.array(json.dumps(meta)), **arrays}))


def load_model(path: str | os.PathLike) -> SdfModel:
    """Read weights written by :func:`save_model`.

    Raises
    ------
    InputError
        Not a model file of this format.
    """
    import zipfile

    where = str(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k.split(":", 1)[1]: z[k] for k in z.files if k.startswith("param:")}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise InputError(f"not a fit-sdf model file ({exc})", where) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError("not a fit-sdf model file", where)
    T = compute()
    net = T.build(int(meta["width"]), int(meta["depth"]), int(meta["frequencies"]), RADIUS, 0)
    try:
        T.load_state(net, arrays)
    except (RuntimeError, KeyError) as exc:
        raise InputError(
            f"model weights do not match its description ({str(exc).splitlines()[0]})", where
        ) from None
    cfg = {k: int(meta[k]) for k in ("width", "depth", "frequencies")}
    return SdfModel(
        net,
        np.asarray(meta["center"], dtype=np.float64),
        float(meta["scale"]),
        field_name(meta["field"]),
        cfg,
    )

"""PyTorch compute for :mod:`recon_cli.stages.learned`: network, training loop, batched queries.

Compute only: the stage (:mod:`recon_cli.stages.learned`) validates every input and turns the
results into grids and meshes. Imported only when a field is fitted or queried, so that
``recon --help`` and every other command never load torch.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

_CHUNK = 65_536  # query points per forward pass (bounds the activations' memory)


class FieldNet(nn.Module):
    """MLP s(x) on Fourier features [x, sin(2^k pi x), cos(2^k pi x)], softplus activations.

    Geometric initialisation (Atzmon & Lipman 2020, with the positional-encoding form of
    Yariv et al. 2020): the weights of the encoded features start at zero and the layers are
    set so that s(x) ~= |x| - radius, a signed distance to a sphere, before any training.
    """

    bands: torch.Tensor  # a registered buffer: 2^k pi per octave

    def __init__(
        self, width: int, depth: int, frequencies: int, radius: float, beta: float = 100.0
    ):
        super().__init__()
        self.frequencies = frequencies
        dims_in = 3 + 6 * frequencies
        layers = []
        d = dims_in
        for i in range(depth):
            lin = nn.Linear(d, width)
            nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(width))
            nn.init.zeros_(lin.bias)
            if i == 0 and frequencies:
                with torch.no_grad():
                    lin.weight[:, 3:] = 0.0
            layers.append(lin)
            d = width
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(d, 1)
        nn.init.normal_(self.out.weight, math.sqrt(math.pi) / math.sqrt(d), 1e-4)
        nn.init.constant_(self.out.bias, -radius)
        self.act = nn.Softplus(beta=beta)
        self.register_buffer(
            "bands", (2.0 ** torch.arange(frequencies, dtype=torch.float32)) * math.pi
        )

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        if not self.frequencies:
            return x
        xb = (x[:, :, None] * self.bands).reshape(len(x), -1)
        return torch.cat([x, torch.sin(xb), torch.cos(xb)], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.encode(x)
        for lin in self.hidden:
            h = self.act(lin(h))
        return self.out(h)[:, 0]


@dataclass
class TrainConfig:
    iterations: int
    max_seconds: float | None
    batch: int
    lr: float
    eikonal_weight: float
    normal_weight: float
    field: str  # "sdf" or "occupancy"
    seed: int
    offsurface_weight: float = 1.0
    surface_weight: float = 1.0
    occupancy_gain: float = 10.0  # p(inside) = sigmoid(-gain * s)
    band: float = (
        0.1  # band samples: offsets N(0, (band * U(0, 1))^2) from random points (eikonal only)
    )
    band_share: float = 0.0  # band samples per surface point
    eikonal_l1: bool = False  # E| |grad s| - 1 | instead of E(|grad s| - 1)^2
    distance_weight: float = 0.0  # E|s(q) - d(q)| on the wide, uniform and band samples
    distance_clamp: float = math.inf  # s and d clamped to [-clamp, clamp] (DeepSDF)
    offset_spread: float = 0.0  # samples p + t n_p, t ~ N(0, spread^2), one per surface point
    offset_weight: float = 0.0  # E|s(p + t n_p) - d| on those kept, d from ``offset_fn``
    eikonal_ramp: float = 0.0  # the eikonal weight rises linearly over this share of the schedule
    eikonal_start: float = 1.0  # from this fraction of ``eikonal_weight``


@dataclass
class TrainOutcome:
    iterations: int
    seconds: float
    interrupted: bool
    best_loss: float
    final_loss: float
    history: list  # (iteration, smoothed loss) every few iterations


def set_threads(n: int | None) -> None:
    if n:
        torch.set_num_threads(int(n))


def build(width: int, depth: int, frequencies: int, radius: float, seed: int) -> FieldNet:
    torch.manual_seed(seed)
    return FieldNet(width, depth, frequencies, radius)


def _grad(y: torch.Tensor, x: torch.Tensor, create_graph: bool) -> torch.Tensor:
    return torch.autograd.grad(y, x, torch.ones_like(y), create_graph=create_graph)[0]


def _eikonal(g: torch.Tensor, l1: bool) -> torch.Tensor:
    dev = g.norm(dim=1) - 1.0
    return dev.abs().mean() if l1 else (dev**2).mean()


def train(
    net: FieldNet,
    points: np.ndarray,
    normals: np.ndarray | None,
    sigma: np.ndarray,
    labels_fn: Callable[[np.ndarray], np.ndarray] | None,
    cfg: TrainConfig,
    on_step: Callable[[int, float, float], None] | None = None,
    distance_fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    offset_fn: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> TrainOutcome:
    """Fit ``net`` to ``points`` (normalised coordinates, (n, 3) float32).

    sdf: L1 zero level on the points + ``normal_weight`` * ||grad s(p) - n_p|| (with normals)
    + ``eikonal_weight`` * (||grad s|| - 1)^2 (``eikonal_l1``: | ||grad s|| - 1 |) on points near
    and away from the surface (IGR) and on ``band_share`` * batch band samples
    + ``distance_weight`` * |clamp(s(q)) - clamp(d(q))| on the wide, uniform and band samples q that
    ``distance_fn`` gives a signed distance d for ((k, 3) float32 -> d (k,) float32, kept (k,)
    bool), both clamped to [-``distance_clamp``, ``distance_clamp``]
    + ``offset_weight`` * |s(x) - d(x)| on samples x = p + t n_p off the surface points along
    their normals (t ~ N(0, ``offset_spread``^2)) that ``offset_fn`` gives a signed distance d
    for ((k, 3) float32, t (k,) float32 -> d (k,) float32, kept (k,) bool). The eikonal weight
    rises linearly from ``eikonal_start`` of it over the first ``eikonal_ramp`` of the schedule.
    occupancy: binary cross-entropy of p(inside) = sigmoid(-gain * s) on labelled samples
    (``labels_fn``: 1 inside) + |s| on the points. On KeyboardInterrupt (at any time, also
    before the first step) the best parameters so far are restored and the outcome says
    ``interrupted``.
    """
    st: dict[str, Any] = {
        "it": 0,
        "ema": None,
        "best": math.inf,
        "last": math.nan,
        "history": [],
        "best_state": {k: v.detach().clone() for k, v in net.state_dict().items()},
    }
    t0 = time.perf_counter()
    interrupted = False
    try:
        fns = (labels_fn, distance_fn, offset_fn)
        _loop(net, points, normals, sigma, fns, cfg, on_step, st, t0)
    except KeyboardInterrupt:
        interrupted = True
    ema = st["ema"]
    if interrupted or (ema is not None and ema > st["best"]):
        net.load_state_dict(st["best_state"])
    elif ema is not None:
        st["best"] = min(st["best"], ema)
    return TrainOutcome(
        st["it"], time.perf_counter() - t0, interrupted, st["best"], st["last"], st["history"]
    )


def _loop(
    net,
    points,
    normals,
    sigma,
    fns: tuple,
    cfg: TrainConfig,
    on_step,
    st: dict,
    t0: float,
) -> None:
    labels_fn, distance_fn, offset_fn = fns
    gen = torch.Generator().manual_seed(cfg.seed)
    pts = torch.from_numpy(points)
    nrm = torch.from_numpy(normals) if normals is not None else None
    sig = torch.from_numpy(sigma)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    while st["it"] < cfg.iterations:
        it = st["it"]
        elapsed = time.perf_counter() - t0
        if cfg.max_seconds is not None and elapsed >= cfg.max_seconds:
            break
        frac = _schedule(opt, cfg, it, elapsed)
        idx, p, off, nb = _samples(pts, sig, cfg, gen)
        if cfg.field == "sdf":
            n_p = None if nrm is None else nrm[idx]
            loss = _sdf_loss(net, p, off, n_p, nb, cfg, distance_fn, _eikonal_weight(cfg, frac))
            if (
                cfg.offset_weight > 0
                and cfg.offset_spread > 0
                and offset_fn is not None
                and n_p is not None
            ):
                loss = loss + _offset_loss(net, p, n_p, cfg, offset_fn, gen)
        else:
            lab = torch.from_numpy(labels_fn(off.numpy()))
            logit = -cfg.occupancy_gain * net(off)
            loss = nn.functional.binary_cross_entropy_with_logits(logit, lab) + net(p).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        _record(net, st, float(loss.detach()), cfg.iterations)
        if on_step is not None:
            on_step(st["it"], st["ema"], time.perf_counter() - t0)


def _schedule(opt, cfg: TrainConfig, it: int, elapsed: float) -> float:
    """Set the step's learning rate: a cosine decay to 2 % over the iterations (or the time).

    Returns the share of the schedule done.
    """
    frac = it / cfg.iterations
    if cfg.max_seconds is not None:
        frac = max(frac, elapsed / cfg.max_seconds)
    lr = cfg.lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(1.0, frac))))
    for g in opt.param_groups:
        g["lr"] = lr
    return min(1.0, frac)


def _eikonal_weight(cfg: TrainConfig, frac: float) -> float:
    """The eikonal weight at ``frac`` of the schedule (ramped in over ``eikonal_ramp``)."""
    if cfg.eikonal_ramp <= 0 or frac >= cfg.eikonal_ramp:
        return cfg.eikonal_weight
    start = cfg.eikonal_start
    return cfg.eikonal_weight * (start + (1.0 - start) * frac / cfg.eikonal_ramp)


def _samples(pts, sig, cfg: TrainConfig, gen) -> tuple:
    """The step's samples: ``(idx, p, off, nb)``.

    ``batch`` surface points ``p`` (rows ``idx``) and the samples off them ``off``: as many
    near (each point's spread), half as many wider, half as many uniform in the box, and ``nb``
    band samples.
    """
    n = len(pts)
    b = cfg.batch
    idx = torch.randint(0, n, (b,), generator=gen)
    p = pts[idx]
    near = p + torch.randn(b, 3, generator=gen) * sig[idx, None]
    wide = p[: b // 2] + torch.randn(b // 2, 3, generator=gen) * 0.1
    unif = torch.rand(b // 2, 3, generator=gen) * 2.0 - 1.0
    nb = int(b * cfg.band_share)
    if nb:
        bi = torch.randint(0, n, (nb,), generator=gen)
        band = pts[bi] + torch.randn(nb, 3, generator=gen) * (
            cfg.band * torch.rand(nb, 1, generator=gen)
        )
        off = torch.cat([near, wide, unif, band])
    else:
        off = torch.cat([near, wide, unif])
    return idx, p, off, nb


def _sdf_loss(
    net, p, off, nrm, nb: int, cfg: TrainConfig, distance_fn, eikonal_weight: float
) -> torch.Tensor:
    """The sdf field's loss on a step's samples (:func:`train`); ``nrm``: the points' normals."""
    b = cfg.batch
    # the wide, uniform and band samples (the near ones are mostly within the points'
    # spacing, where the distance to the points is not the surface's)
    d0 = b
    use_dist = cfg.distance_weight > 0 and distance_fn is not None and nb > 0
    if use_dist:
        d_np, keep_np = distance_fn(off[d0:].numpy())
        dist_t, keep_t = torch.from_numpy(d_np), torch.from_numpy(keep_np)
    p.requires_grad_(True)
    off.requires_grad_(True)
    sp = net(p)
    so = net(off)
    go = _grad(so, off, True)
    loss = cfg.surface_weight * sp.abs().mean()
    eik = _eikonal(go, cfg.eikonal_l1)
    if nrm is not None:
        gp = _grad(sp, p, True)
        loss = loss + cfg.normal_weight * (gp - nrm).norm(dim=1).mean()
        eik = 0.5 * eik + 0.5 * _eikonal(gp, cfg.eikonal_l1)
    loss = loss + eikonal_weight * eik
    if cfg.offsurface_weight and nrm is not None:
        # SIREN's off-surface term: no zero level away from the points (with normals
        # only: without them nothing holds the slope and it fights the zero level)
        far = so[b : 2 * b]
        loss = loss + cfg.offsurface_weight * torch.exp(-100.0 * far.abs()).mean()
    if use_dist and bool(keep_t.any()):
        c = cfg.distance_clamp
        dev = (so[d0:].clamp(-c, c) - dist_t.clamp(-c, c)).abs()[keep_t]
        loss = loss + cfg.distance_weight * dev.sum() / len(keep_t)
    return loss


def _offset_loss(net, p, nrm, cfg: TrainConfig, offset_fn, gen) -> torch.Tensor:
    """The distance term on samples off the points ``p`` along their normals ``nrm``."""
    t = torch.randn(len(p), generator=gen) * cfg.offset_spread
    x = p.detach() + t[:, None] * nrm
    d_np, keep_np = offset_fn(x.numpy(), t.numpy())
    keep = torch.from_numpy(keep_np)
    if not bool(keep.any()):
        return torch.zeros(())
    dev = (net(x[keep]) - torch.from_numpy(d_np)[keep]).abs()
    return cfg.offset_weight * dev.sum() / len(keep)


def _record(net, st: dict, last: float, iterations: int) -> None:
    """Count the step; the smoothed loss, its history and the best parameters so far."""
    st["it"] = it = st["it"] + 1
    st["last"] = last
    ema = last if st["ema"] is None else 0.95 * st["ema"] + 0.05 * last
    st["ema"] = ema
    if it % 10 == 0 or it == iterations:
        st["history"].append((it, ema))
        if ema < st["best"]:
            st["best"] = ema
            st["best_state"] = {k: v.detach().clone() for k, v in net.state_dict().items()}


def values(net: FieldNet, x: np.ndarray, chunk: int = _CHUNK) -> np.ndarray:
    """Network output at (k, 3) normalised points, float32."""
    out = np.empty(len(x), np.float32)
    with torch.no_grad():
        for i in range(0, len(x), chunk):
            xi = torch.from_numpy(np.ascontiguousarray(x[i : i + chunk], dtype=np.float32))
            out[i : i + chunk] = net(xi).numpy()
    return out


def gradients(
    net: FieldNet, x: np.ndarray, chunk: int = _CHUNK // 4
) -> tuple[np.ndarray, np.ndarray]:
    """Network output and its gradient (autodiff) at (k, 3) normalised points."""
    val = np.empty(len(x), np.float32)
    grad = np.empty((len(x), 3), np.float32)
    for i in range(0, len(x), chunk):
        xi = torch.from_numpy(
            np.ascontiguousarray(x[i : i + chunk], dtype=np.float32)
        ).requires_grad_(True)
        y = net(xi)
        g = _grad(y, xi, False)
        val[i : i + chunk] = y.detach().numpy()
        grad[i : i + chunk] = g.numpy()
    return val, grad


def state_arrays(net: FieldNet) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}


def load_state(net: FieldNet, arrays: dict[str, np.ndarray]) -> None:
    net.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in arrays.items()})

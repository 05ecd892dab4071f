"""Simulated depth sensors for tests and benches: organized clouds as real cameras write them.

A :class:`DepthCamera` (pinhole, ``width`` x ``height`` pixels) ray-casts a scene given by a
signed distance function (sphere tracing, so unions of the analytic shapes of
:mod:`shapes`, planes and boxes make rooms and tabletops) and returns an *organized*
cloud: an ``(height, width, 3)`` array in world coordinates with NaN where a ray hits nothing
within range, as Kinect/RealSense drivers and PCL write them. Sensor effects, each optional:

- depth noise along the ray growing with the square of the distance (Kinect v1:
  ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)**2`` metres, Nguyen, Izadi & Lovell 2012, scaled
  by ``noise``),
- flying pixels: at depth discontinuities a fraction of the pixels take a depth between
  the foreground and the background (the mixed returns at silhouettes),
- depth quantisation (``disparity_bits``) is not modelled.

:func:`write_organized_pcd` writes such a cloud as a PCD (binary, ASCII or binary_compressed)
with ``WIDTH``/``HEIGHT``, NaN pixels, packed ``rgba`` colour and the ``VIEWPOINT`` of the
camera, as PCL does; :func:`exact_image` and :func:`true_normals` give the noise-free points
and the scene's normals to measure against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shapes import random_rotation, rounded_box_sdf, sphere_sdf, torus_sdf


# ---- scenes: signed distance functions (n, 3) -> (n,) ----------------------------------------
def plane_sdf(p, normal=(0.0, 0.0, 1.0), offset=0.0):
    """Half-space below the plane ``normal . p = offset`` (negative inside)."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    return p @ n - offset


def box_sdf(p, lo, hi):
    """Exact signed distance of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def union(*fns):
    """The union of solids: the minimum of their distances."""
    return lambda p: np.min(np.stack([f(p) for f in fns]), axis=0)


def tabletop_scene():
    """A tabletop scene's sdf, in metres: a room corner 3 m across.

    A floor slab (z in [-0.05, 0]), a back wall, a sphere, a torus lying down and a rounded box.
    """
    floor = lambda p: box_sdf(p, (-1.5, -1.5, -0.05), (1.5, 1.5, 0.0))  # noqa: E731
    wall = lambda p: box_sdf(p, (-1.5, 1.45, -0.05), (1.5, 1.5, 1.5))  # noqa: E731
    ball = lambda p: sphere_sdf(p - (-0.5, 0.2, 0.3), 0.3)  # noqa: E731
    ring = lambda p: torus_sdf(p - (0.5, -0.2, 0.12), 0.3, 0.1)  # noqa: E731
    block = lambda p: rounded_box_sdf(p - (0.3, 0.7, 0.25), half=(0.25, 0.2, 0.25), radius=0.04)  # noqa: E731
    return union(floor, wall, ball, ring, block)


# ---- cluttered rooms (issue 45): furniture and people as parts with bounding boxes -----------
@dataclass
class Part:
    """A solid's signed distance (or a lower bound of it outside) and a box holding the solid."""

    sdf: object
    lo: np.ndarray
    hi: np.ndarray


def bounded_union(parts: list[Part], *unbounded):
    """The union of ``parts`` and ``unbounded`` solids, parts evaluated only near their box.

    A part is evaluated only where its box is nearer than the nearest solid so far (exact: its
    distance is at least its box's).
    """
    lo = np.array([q.lo for q in parts])
    hi = np.array([q.hi for q in parts])

    def sdf(p):
        best = np.full(len(p), np.inf)
        for fn in unbounded:
            best = np.minimum(best, fn(p))
        for j, part in enumerate(parts):
            gap = np.maximum(lo[j] - p, p - hi[j])
            np.maximum(gap, 0.0, out=gap)
            idx = np.flatnonzero(np.einsum("ij,ij->i", gap, gap) < best**2)
            if len(idx):
                best[idx] = np.minimum(best[idx], part.sdf(p[idx]))
        return best

    return sdf


def capsule_sdf(p, a, b, r):
    """A segment ``a``-``b`` thickened by ``r``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ab, axis=1) - r


def cylinder_sdf(p, x, y, z0, z1, r):
    """A vertical cylinder of radius ``r`` around (x, y), from height ``z0`` to ``z1``."""
    q = np.stack(
        [np.hypot(p[:, 0] - x, p[:, 1] - y) - r, np.maximum(z0 - p[:, 2], p[:, 2] - z1)], 1
    )
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


# local solids: (sdf, box lo, box hi) in a piece of furniture's frame (z up, origin on the floor)
def _box(lo, hi):
    return (lambda p: box_sdf(p, lo, hi)), np.asarray(lo, float), np.asarray(hi, float)


def _capsule(a, b, r):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return (lambda p: capsule_sdf(p, a, b, r)), np.minimum(a, b) - r, np.maximum(a, b) + r


def _ball(c, r):
    c = np.asarray(c, float)
    return (lambda p: np.linalg.norm(p - c, axis=1) - r), c - r, c + r


def _cyl(x, y, z0, z1, r):
    return (
        (lambda p: cylinder_sdf(p, x, y, z0, z1, r)),
        np.array([x - r, y - r, z0]),
        np.array([x + r, y + r, z1]),
    )


def _rbox(c, half, radius):
    c, half = np.asarray(c, float), np.asarray(half, float)
    return (lambda p: rounded_box_sdf(p - c, half=half, radius=radius)), c - half, c + half


def _placed(items, at, yaw: float) -> list[Part]:
    """Local solids turned by ``yaw`` (radians, about z) and moved to ``at``, as one part.

    The part is a union of its own, so that the scene's union skips the whole piece far from it.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # local -> world
    at = np.asarray(at, float)
    local = bounded_union([Part(*it) for it in items])
    lo = np.min([it[1] for it in items], axis=0)
    hi = np.max([it[2] for it in items], axis=0)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    w = corners @ rot.T + at
    return [Part(lambda p: local((p - at) @ rot), w.min(0), w.max(0))]


def _desk(rng, w, d):
    h = rng.uniform(0.70, 0.76)
    leg = rng.uniform(0.015, 0.025)  # thin round legs
    items = [_box((-w / 2, -d / 2, h - 0.03), (w / 2, d / 2, h))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            items.append(_cyl(sx * (w / 2 - 0.05), sy * (d / 2 - 0.05), 0.0, h - 0.03, leg))
    # a monitor (a panel 2-3 cm thick on a thin stand), a keyboard, a mug, books
    mw, mh, mt = rng.uniform(0.45, 0.6), rng.uniform(0.28, 0.36), rng.uniform(0.02, 0.03)
    my = d / 2 - 0.15
    items += [
        _box((-mw / 2, my - mt, h + 0.12), (mw / 2, my, h + 0.12 + mh)),
        _cyl(0.0, my + 0.03, h, h + 0.14, 0.015),
        _box((-0.12, my - 0.05, h), (0.12, my + 0.1, h + 0.012)),
        _box((-0.22, -0.05, h), (0.22, 0.1, h + 0.02)),
        _cyl(w / 2 - 0.2, 0.0, h, h + 0.1, 0.04),
    ]
    for _ in range(rng.integers(0, 4)):
        x = rng.uniform(-w / 2 + 0.1, -0.3)
        bw, bd, bh = rng.uniform(0.15, 0.3), rng.uniform(0.1, 0.25), rng.uniform(0.02, 0.06)
        items.append(_box((x, -bd / 2, h), (x + bw, bd / 2, h + bh)))
    return items


def _chair(rng):
    seat = rng.uniform(0.42, 0.48)
    if rng.random() < 0.5:  # four thin legs
        r = rng.uniform(0.01, 0.018)
        items = [_cyl(sx * 0.2, sy * 0.2, 0.0, seat - 0.04, r) for sx in (-1, 1) for sy in (-1, 1)]
        items += [_box((-0.23, -0.23, seat - 0.04), (0.23, 0.23, seat))]
        items += [_box((-0.22, 0.2, seat), (0.22, 0.225, seat + rng.uniform(0.35, 0.45)))]
        return items
    # an office chair: five spokes, a pole, a padded seat and back
    items = [_cyl(0.0, 0.0, 0.06, seat - 0.05, 0.025)]
    for k in range(5):
        a = 2 * np.pi * k / 5 + rng.uniform(0, 1)
        items.append(_capsule((0.0, 0.0, 0.07), (0.3 * np.cos(a), 0.3 * np.sin(a), 0.05), 0.02))
    items += [
        _rbox((0.0, 0.0, seat - 0.03), (0.24, 0.24, 0.05), 0.03),
        _capsule((0.0, 0.24, seat), (0.0, 0.26, seat + 0.2), 0.02),
        _rbox((0.0, 0.27, seat + 0.4), (0.23, 0.04, 0.22), 0.03),
    ]
    return items


def _shelf(rng, w):
    d, h = rng.uniform(0.28, 0.4), rng.uniform(1.6, 2.1)
    t = 0.02
    items = [
        _box((-w / 2, -d / 2, 0.0), (-w / 2 + t, d / 2, h)),
        _box((w / 2 - t, -d / 2, 0.0), (w / 2, d / 2, h)),
        _box((-w / 2, d / 2 - 0.01, 0.0), (w / 2, d / 2, h)),
    ]
    levels = np.linspace(0.05, h - t, rng.integers(4, 6))
    for k, z in enumerate(levels):
        items.append(_box((-w / 2, -d / 2, z), (w / 2, d / 2, z + t)))
        if k == len(levels) - 1:
            break
        x = -w / 2 + t
        while x < w / 2 - 0.12 and rng.random() < 0.9:  # books, upright, some gaps
            bt = rng.uniform(0.02, 0.07)
            bh = min(rng.uniform(0.15, 0.3), levels[k + 1] - z - 0.03)
            if rng.random() < 0.8:
                items.append(_box((x, -d / 2 + 0.03, z + t), (x + bt, d / 2 - 0.02, z + t + bh)))
            x += bt + rng.uniform(0.0, 0.03)
    return items


def _person(rng, sitting: bool = False):
    """Standing (or sitting) at the origin, facing -y: limbs 4-7 cm thick."""
    hip = 0.5 if sitting else rng.uniform(0.85, 0.95)
    top = hip + rng.uniform(0.55, 0.65)
    items = [_rbox((0.0, 0.0, (hip + top) / 2), (0.19, 0.11, (top - hip) / 2 + 0.04), 0.08)]
    items += [_capsule((0.0, 0.0, top), (0.0, 0.0, top + 0.08), 0.05)]
    items += [_ball((0.0, rng.uniform(-0.02, 0.02), top + 0.2), rng.uniform(0.1, 0.12))]
    for sx in (-1, 1):
        h = (sx * 0.1, 0.0, hip)
        if sitting:
            knee = (sx * 0.12, -0.45, hip + 0.02)
            items += [_capsule(h, knee, 0.07), _capsule(knee, (sx * 0.13, -0.5, 0.06), 0.055)]
        else:
            step = rng.uniform(-0.25, 0.25) * sx
            items += [_capsule(h, (sx * 0.12, step, 0.07), 0.065)]
        sh = np.array([sx * 0.25, 0.0, top - 0.05])
        pose = rng.integers(4)
        if pose == 0:  # down
            elbow, hand = sh + (sx * 0.03, 0.02, -0.28), sh + (sx * 0.04, -0.05, -0.55)
        elif pose == 1:  # out to the side
            elbow, hand = sh + (sx * 0.28, 0.0, -0.05), sh + (sx * 0.55, -0.05, -0.02)
        elif pose == 2:  # forward (pointing, holding)
            elbow, hand = sh + (0.0, -0.2, -0.2), sh + (-sx * 0.05, -0.45, -0.15)
        else:  # on the hip
            elbow, hand = sh + (sx * 0.18, 0.05, -0.22), sh + (sx * 0.02, 0.0, -0.4)
        items += [_capsule(sh, elbow, 0.045), _capsule(elbow, hand, 0.038)]
    return items


def _lamp(rng):
    h = rng.uniform(1.4, 1.7)
    return [
        _cyl(0.0, 0.0, 0.0, 0.02, 0.15),
        _cyl(0.0, 0.0, 0.02, h, 0.012),
        _ball((0.0, 0.0, h + 0.1), 0.15),
    ]


def _plant(rng):
    items = [_cyl(0.0, 0.0, 0.0, 0.3, 0.15)]
    for _ in range(rng.integers(4, 8)):
        tip = np.array([rng.uniform(-0.35, 0.35), rng.uniform(-0.35, 0.35), rng.uniform(0.6, 1.1)])
        items += [_capsule((0.0, 0.0, 0.3), tip, 0.008), _ball(tip, rng.uniform(0.05, 0.1))]
    return items


@dataclass
class Scene:
    """A cluttered scene: its sdf, the camera's place and target, surfaces returning nothing."""

    sdf: object
    eye: np.ndarray
    target: np.ndarray
    absorb: object = None

    def camera(self, width: int = 640, height: int = 480) -> DepthCamera:
        """A Kinect v1 at the scene's viewpoint (57 degrees, returns from 0.5 to 8 m)."""
        return DepthCamera(
            eye=self.eye,
            rotation=look_at(self.eye, self.target),
            width=width,
            height=height,
            max_range=8.0,
            min_range=0.5,
        )

    def image(self, width: int, height: int, seed: int, **effects) -> np.ndarray:
        """The organized cloud (height, width, 3) of a Kinect v1 with every sensor effect.

        Every effect of :class:`SensorEffects` (``effects`` overrides its fields), noise seeded by
        ``seed``.
        """
        fx = SensorEffects(absorb=self.absorb, **effects)
        rng = np.random.default_rng(seed)
        return depth_image(self.camera(width, height), self.sdf, rng, effects=fx)


class _Floor:
    """Free spots on a room's floor (discs that do not overlap)."""

    def __init__(self, rng, lo, hi):
        self.rng, self.lo, self.hi, self.taken = (
            rng,
            np.asarray(lo, float),
            np.asarray(hi, float),
            [],
        )

    def spot(self, radius: float, lo=None, hi=None, tries: int = 60):
        lo = self.lo + radius if lo is None else np.asarray(lo, float)
        hi = self.hi - radius if hi is None else np.asarray(hi, float)
        for _ in range(tries):
            c = self.rng.uniform(lo, hi)
            if all(np.hypot(*(c - q)) > radius + r for q, r in self.taken):
                self.taken.append((c, radius))
                return np.array([c[0], c[1], 0.0])
        return None


def _room(lo, hi, recesses=()):
    """The inside of a box (walls, floor, ceiling) with box-shaped recesses (doors, alcoves)."""
    boxes = [(np.asarray(lo, float), np.asarray(hi, float)), *recesses]
    return lambda p: -np.min(np.stack([box_sdf(p, a, b) for a, b in boxes]), axis=0)


def office_scene(seed: int) -> Scene:
    """A cluttered office, walls and floor out to 5-8 m, a window returning nothing.

    Desks with monitors, chairs, shelves of books, cabinets, a lamp, a plant, boxes, people.
    """
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(4.5, 7.0), rng.uniform(6.0, 8.0), rng.uniform(2.6, 3.0)
    lo, hi = np.array([-W / 2, 0.0]), np.array([W / 2, D])
    floor = _Floor(rng, lo, hi)
    floor.taken.append((np.array([0.0, 0.3]), 0.5))  # the camera's spot
    parts: list[Part] = []
    for _ in range(rng.integers(2, 5)):
        w, d = rng.uniform(1.2, 1.8), rng.uniform(0.6, 0.8)
        at = floor.spot(0.55 * np.hypot(w, d) + 0.4)
        if at is None:
            continue
        yaw = rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2]) + rng.uniform(-0.2, 0.2)
        parts += _placed(_desk(rng, w, d), at, yaw)
        chair = at + np.array([np.sin(yaw), -np.cos(yaw), 0.0]) * (d / 2 + 0.15)
        parts += _placed(_chair(rng), chair, yaw + rng.uniform(-0.5, 0.5))
    for x in rng.uniform(-W / 2 + 0.7, W / 2 - 0.7, rng.integers(2, 4)):  # shelves on the walls
        side = rng.integers(3)
        w = rng.uniform(0.8, 1.2)
        if side == 0:  # the back wall
            parts += _placed(_shelf(rng, w), (x, D - 0.2, 0.0), np.pi)
        else:
            y = rng.uniform(1.5, D - 1.0)
            sx = -1 if side == 1 else 1
            parts += _placed(_shelf(rng, w), (sx * (W / 2 - 0.2), y, 0.0), -sx * np.pi / 2)
    items = [("cabinet", 0.5), ("person", 0.4), ("person", 0.4), ("lamp", 0.2), ("plant", 0.4)]
    items += [("box", 0.35)] * int(rng.integers(2, 5)) + [("chair", 0.35), ("ball", 0.2)]
    for kind, radius in items:
        at = floor.spot(radius)
        if at is None:
            continue
        yaw = rng.uniform(-np.pi, np.pi)
        if kind == "cabinet":
            half = (rng.uniform(0.3, 0.5), rng.uniform(0.2, 0.3), rng.uniform(0.35, 0.65))
            parts += _placed([_rbox((0.0, 0.0, half[2]), half, 0.02)], at, yaw)
        elif kind == "person":
            parts += _placed(_person(rng, sitting=rng.random() < 0.3), at, yaw)
        elif kind == "box":
            half = rng.uniform(0.12, 0.3, 3)
            parts += _placed(
                [_box((-half[0], -half[1], 0.0), (half[0], half[1], 2 * half[2]))], at, yaw
            )
        elif kind == "ball":
            r = rng.uniform(0.1, 0.2)
            parts += _placed([_ball((0.0, 0.0, r), r)], at, 0.0)
        else:
            parts += _placed({"lamp": _lamp, "plant": _plant, "chair": _chair}[kind](rng), at, yaw)
    # a near object (0.5-1 m from the camera)
    near = np.array([rng.uniform(-0.4, 0.4), rng.uniform(0.9, 1.3), 0.0])
    parts += _placed(_chair(rng), near, rng.uniform(-np.pi, np.pi))
    door = (np.array([W / 2 - 0.01, 2.0, 0.0]), np.array([W / 2 + 0.25, 2.9, 2.05]))
    sdf = bounded_union(parts, _room((-W / 2, 0.0, 0.0), (W / 2, D, H), [door]))
    wx = rng.uniform(-W / 2 + 1.0, W / 2 - 2.0)

    def window(p):
        return (p[:, 1] > D - 0.02) & (abs(p[:, 0] - wx - 0.6) < 0.6) & (abs(p[:, 2] - 1.6) < 0.6)

    eye = np.array([rng.uniform(-W / 4, W / 4), rng.uniform(0.15, 0.4), rng.uniform(1.0, 1.7)])
    target = np.array(
        [rng.uniform(-W / 3, W / 3), D * rng.uniform(0.6, 0.9), rng.uniform(0.3, 0.9)]
    )
    return Scene(sdf, eye, target, window)


def people_scene(seed: int) -> Scene:
    """A hall with 3-6 people (standing, sitting, arms out) at 1-7 m, a table and chairs."""
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(6.0, 9.0), rng.uniform(6.5, 8.5), rng.uniform(2.8, 3.5)
    floor = _Floor(rng, (-W / 2, 0.0), (W / 2, D))
    floor.taken.append((np.array([0.0, 0.3]), 0.6))
    parts: list[Part] = []
    at = floor.spot(1.2, lo=(-W / 4, 3.0), hi=(W / 4, 6.0))
    if at is not None:
        w, d = rng.uniform(1.4, 2.0), rng.uniform(0.8, 1.0)
        items = _desk(rng, w, d)[:5]  # a bare table
        parts += _placed(items, at, rng.uniform(-0.3, 0.3))
    for _ in range(rng.integers(3, 7)):
        dist = rng.uniform(1.0, 7.0)
        c = floor.spot(
            0.45,
            lo=(-min(W / 2 - 0.5, 0.5 * dist + 0.5), dist),
            hi=(min(W / 2 - 0.5, 0.5 * dist + 0.5), dist + 0.3),
        )
        if c is None:
            continue
        sitting = rng.random() < 0.3
        yaw = rng.uniform(-np.pi, np.pi)
        if sitting:
            parts += _placed(_chair(rng), c + [0.0, 0.0, 0.0], yaw)
        parts += _placed(_person(rng, sitting), c, yaw)
    for _ in range(rng.integers(2, 5)):
        c = floor.spot(0.35)
        if c is not None:
            parts += _placed(_chair(rng), c, rng.uniform(-np.pi, np.pi))
    sdf = bounded_union(parts, _room((-W / 2, 0.0, 0.0), (W / 2, D, H)))
    eye = np.array([rng.uniform(-0.5, 0.5), 0.3, rng.uniform(1.1, 1.6)])
    target = np.array([rng.uniform(-0.5, 0.5), 4.0, rng.uniform(0.6, 1.1)])
    return Scene(sdf, eye, target)


def corridor_scene(seed: int) -> Scene:
    """A corridor longer than the sensor's range, seen from beside one wall.

    Both walls and the floor at grazing angles, door recesses, cabinets, a bin, people walking.
    """
    rng = np.random.default_rng(seed)
    W, H, L = rng.uniform(2.0, 2.8), rng.uniform(2.4, 2.9), 14.0
    recesses = []
    for y in np.arange(rng.uniform(1.5, 3.0), L - 1.0, rng.uniform(2.5, 4.0)):
        sx = rng.choice([-1, 1])
        x0, x1 = sorted((sx * W / 2, sx * (W / 2 + 0.2)))
        recesses.append((np.array([x0, y, 0.0]), np.array([x1, y + 0.9, 2.05])))
    floor = _Floor(rng, (-W / 2, 0.0), (W / 2, L))
    floor.taken.append((np.array([0.0, 0.3]), 0.5))
    parts: list[Part] = []
    for y in rng.uniform(2.0, 9.0, rng.integers(1, 3)):
        sx = rng.choice([-1, 1])
        half = (0.4, 0.2, rng.uniform(0.4, 0.9))
        parts += _placed(
            [_rbox((0.0, 0.0, half[2]), half, 0.02)], (sx * (W / 2 - 0.21), y, 0.0), 0.0
        )
    c = floor.spot(0.2)
    if c is not None:
        parts += _placed([_cyl(0.0, 0.0, 0.0, 0.6, 0.17)], c, 0.0)
    for _ in range(rng.integers(1, 4)):
        c = floor.spot(0.45, lo=(-W / 2 + 0.5, 1.5), hi=(W / 2 - 0.5, 8.0))
        if c is not None:
            parts += _placed(_person(rng), c, rng.choice([0.0, np.pi]) + rng.uniform(-0.3, 0.3))
    sdf = bounded_union(parts, _room((-W / 2, 0.0, 0.0), (W / 2, L, H), recesses))
    sx = rng.choice([-1, 1])
    eye = np.array([sx * (W / 2 - rng.uniform(0.35, 0.7)), 0.2, rng.uniform(1.1, 1.7)])
    target = np.array([-sx * rng.uniform(0.0, 0.5), 6.0, rng.uniform(0.4, 1.0)])
    return Scene(sdf, eye, target)


CLUTTERED = {"office": office_scene, "people": people_scene, "corridor": corridor_scene}


def cluttered_cloud(kind: str, seed: int, width: int = 160, height: int = 120):
    """A :data:`CLUTTERED` scene's image as valid points, moved far, and the camera's place.

    Points (n, 3) rotated and moved by up to 1e6 (seeded by ``seed``); the camera's place (3,) in
    that frame.
    """
    scene = CLUTTERED[kind](seed)
    p = valid_rows(scene.image(width, height, seed))
    rng = np.random.default_rng(seed)
    rot, off = random_rotation(rng), rng.uniform(-1e6, 1e6, 3)
    return p @ rot.T + off, scene.eye @ rot.T + off


# ---- the camera ------------------------------------------------------------------------------
def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotation (columns: right, down, forward), as an optical frame."""
    eye, target, up = (np.asarray(x, float) for x in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return np.stack([r, d, f], axis=1)


@dataclass
class DepthCamera:
    """A pinhole depth camera.

    Parameters
    ----------
    eye : (3,) float
        Optical centre in world coordinates.
    rotation : (3, 3) float
        Camera-to-world rotation; column 2 is the viewing direction (:func:`look_at`).
    width, height : int
        Image size in pixels.
    fov : float
        Horizontal field of view, degrees (Kinect v1: 57).
    max_range : float
        Rays hitting nothing closer than this give NaN pixels.
    min_range : float
        Hits closer than this give NaN pixels (Kinect v1: about 0.5 m).
    """

    eye: np.ndarray
    rotation: np.ndarray
    width: int = 160
    height: int = 120
    fov: float = 57.0
    max_range: float = 6.0
    min_range: float = 0.0

    @property
    def focal(self) -> float:
        """Focal length in pixels, from the width and the horizontal field of view."""
        return 0.5 * self.width / np.tan(np.radians(self.fov) / 2)

    def rays(self) -> np.ndarray:
        """(height, width, 3) unit ray directions in world coordinates."""
        f = self.focal
        u = (np.arange(self.width) + 0.5 - self.width / 2) / f
        v = (np.arange(self.height) + 0.5 - self.height / 2) / f
        uu, vv = np.meshgrid(u, v)
        d = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ self.rotation.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def cast(self, sdf, steps: int = 300, eps: float = 1e-6) -> np.ndarray:
        """(height, width) distance along each ray to the first hit (inf for a miss)."""
        t, hit = sphere_trace(sdf, self.eye, self.rays().reshape(-1, 3), self.max_range, steps, eps)
        t[~hit | (t > self.max_range) | (t < self.min_range)] = np.inf
        return t.reshape(self.height, self.width)


def sphere_trace(sdf, o, d: np.ndarray, t_max, steps: int, eps: float):
    """Sphere-trace rays from ``o`` along unit ``d`` up to ``t_max``.

    ``o``: (3,) or (n, 3); ``d``: (n, 3); ``t_max``: scalar or (n,). Returns (n,) distances reached
    and (n,) whether the ray came within ``eps`` of the scene.
    """
    o = np.asarray(o, float)
    t_max = np.broadcast_to(np.asarray(t_max, float), (len(d),))
    t = np.zeros(len(d))
    live = np.ones(len(d), bool)
    hit = np.zeros(len(d), bool)
    for _ in range(steps):
        idx = np.flatnonzero(live)
        if len(idx) == 0:
            break
        f = sdf((o if o.ndim == 1 else o[idx]) + t[idx, None] * d[idx])
        close = f < eps
        hit[idx[close]] = True
        t[idx] += np.where(close, 0.0, np.maximum(f, 0.0))
        live[idx[close | (t[idx] > t_max[idx])]] = False
    return t, hit


def depth_image(
    camera: DepthCamera,
    sdf,
    rng: np.random.Generator,
    *,
    noise: float = 1.0,
    flying: float = 0.5,
    effects: SensorEffects | None = None,
) -> np.ndarray:
    """An organized cloud of ``sdf`` seen by ``camera``.

    (height, width, 3), NaN where nothing is hit.

    Parameters
    ----------
    noise : float
        Scale of the Kinect-like depth noise (0: exact hits).
    flying : float
        Fraction of the pixels at a depth edge (a neighbour more than 5 % farther) that
        become flying pixels, their depth drawn uniformly between the two surfaces.
    effects : SensorEffects, optional
        The other effects of a real sensor (holes, correlated noise, quantisation); None: none.
    """
    t = camera.cast(sdf)
    if effects is not None:
        t = effects.holes(camera, sdf, t, rng)
    z = t.copy()
    if flying > 0:
        finite = np.isfinite(t)
        near = np.where(finite, t, 0.0)
        # the farthest finite 4-neighbour (misses make no mixed return)
        pad = np.pad(near, 1)
        nb = np.maximum.reduce([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
        edge = finite & (nb > 1.05 * near)
        pick = edge & (rng.random(t.shape) < flying)
        z[pick] = near[pick] + rng.random(int(pick.sum())) * (nb[pick] - near[pick])
    if noise > 0:
        sigma = noise * (0.0012 + 0.0019 * (np.where(np.isfinite(z), z, 0.4) - 0.4) ** 2)
        if effects is None:
            z = z + rng.normal(size=z.shape) * sigma
        else:
            z = effects.noisy(z, sigma, rng)
    pts = camera.eye + camera.rays() * z[..., None]
    pts[~np.isfinite(z)] = np.nan
    return pts


@dataclass
class SensorEffects:
    """What a real structured-light camera (Kinect v1) does beyond white depth noise.

    Parameters
    ----------
    shadow : float
        Baseline (metres) of the projector, to the camera's right: pixels whose surface the
        projector does not light are NaN (the bands beside every foreground edge); 0: none.
    grazing : float
        Incidence angle (degrees) from which returns fade: a pixel seen at angle ``a`` is NaN
        with probability ``(a - grazing) / (90 - grazing)``.
    blobs : float
        Fraction of the image lost in random blobs (dark, glossy or sunlit patches).
    absorb : callable, optional
        ``(n, 3) points -> (n,) bool``: surfaces that return nothing (windows, screens).
    correlation : float
        Pixels over which the depth noise is correlated (the sensor's matching window); 0:
        white noise.
    disparity : float
        Disparity quantum in 1/metres (Kinect v1 at 640 pixels: 1/8 pixel over
        focal x baseline = 0.125 / (580 x 0.075) = 0.0029): depths come in steps of
        ``disparity z**2``; 0: continuous.
    """

    shadow: float = 0.075
    grazing: float = 75.0
    blobs: float = 0.02
    absorb: object = None
    correlation: float = 1.5
    disparity: float = 0.0029

    def holes(self, camera: DepthCamera, sdf, t: np.ndarray, rng) -> np.ndarray:
        """``t`` (height, width) with the pixels the sensor loses set to inf."""
        t = t.copy()
        rays = camera.rays()
        hit = np.isfinite(t)
        p = camera.eye + rays[hit] * t[hit][:, None]
        lost = np.zeros(len(p), bool)
        if self.absorb is not None:
            lost |= np.asarray(self.absorb(p), bool)
        nrm = true_normals(sdf, p)
        cos = np.abs(np.einsum("ij,ij->i", nrm, rays[hit]))
        angle = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
        fade = np.clip((angle - self.grazing) / (90.0 - self.grazing), 0.0, 1.0)
        lost |= rng.random(len(p)) < fade
        if self.shadow > 0:
            lost |= _shadowed(sdf, p, nrm, camera.eye + self.shadow * camera.rotation[:, 0])
        t.reshape(-1)[np.flatnonzero(hit.reshape(-1))[lost]] = np.inf
        if self.blobs > 0:
            field = _smooth_field(t.shape, 0.04 * t.shape[1], rng)
            t[field > np.quantile(field, 1.0 - self.blobs)] = np.inf
        return t

    def noisy(self, z: np.ndarray, sigma: np.ndarray, rng) -> np.ndarray:
        """``z`` with noise of standard deviation ``sigma`` (correlated), then quantised."""
        e = (
            rng.normal(size=z.shape)
            if self.correlation <= 0
            else _smooth_field(z.shape, self.correlation, rng)
        )
        if self.disparity > 0:
            # the quantisation's own error (uniform, a step wide) is part of the measured sigma
            step = self.disparity * np.where(np.isfinite(z), z, 0.0) ** 2
            sigma = np.sqrt(np.maximum(sigma**2 - step**2 / 12, 0.0))
        z = z + e * sigma
        if self.disparity > 0:
            with np.errstate(divide="ignore"):
                z = 1.0 / (np.round(1.0 / (z * self.disparity)) * self.disparity)
        return z


def _smooth_field(shape, width: float, rng) -> np.ndarray:
    """Gaussian noise smoothed over ``width`` pixels, unit standard deviation."""
    from scipy.ndimage import gaussian_filter

    f = gaussian_filter(rng.normal(size=shape), width, mode="wrap")
    return f / f.std()


def _shadowed(
    sdf, p: np.ndarray, nrm: np.ndarray, light: np.ndarray, steps: int = 200
) -> np.ndarray:
    """(n,) True where the segment from ``p`` (off its surface) to ``light`` hits the scene."""
    d = light - p
    length = np.linalg.norm(d, axis=1)
    d /= length[:, None]
    # start a little off the surface, towards the light (the normal's side facing it)
    side = np.sign(np.einsum("ij,ij->i", nrm, d))
    o = p + 2e-3 * side[:, None] * nrm
    t, hit = sphere_trace(sdf, o, d, length, steps, 1e-5)
    return hit & (t < length)


def valid_rows(organized: np.ndarray) -> np.ndarray:
    """The finite points of an organized cloud, (n, 3), in row-major pixel order."""
    p = organized.reshape(-1, 3)
    return p[np.isfinite(p).all(axis=1)]


# ---- files as PCL writes them ------------------------------------------------------------------
def write_organized_pcd(
    path,
    organized: np.ndarray,
    camera: DepthCamera | None = None,
    colors=None,
    data: str = "binary",
    dtype: str = "f4",
) -> None:
    """PCD of an organized cloud as PCL writes it.

    ``WIDTH``/``HEIGHT`` of the image, NaN pixels kept, ``rgba`` packed as PCL packs it (0xAARRGGBB
    in 4 bytes), ``VIEWPOINT`` of the camera (position and orientation quaternion w x y z).

    ``data``: ``binary`` (PCL's default), ``ascii`` (NaN written ``nan``) or ``binary_compressed``
    (column-major, LZF: written as literal runs, which every LZF reader decodes); ``dtype``: ``f4``
    (as depth cameras give) or ``f8`` coordinates.
    """
    h, w, _ = organized.shape
    n = h * w
    ftype = "<" + dtype
    rows = np.zeros(n, dtype=[("x", ftype), ("y", ftype), ("z", ftype), ("rgba", "<u4")])
    p = organized.reshape(-1, 3)
    rows["x"], rows["y"], rows["z"] = p[:, 0], p[:, 1], p[:, 2]
    if colors is None:
        colors = np.full((n, 3), 200, np.uint8)
    c = np.asarray(colors, np.uint32).reshape(-1, 3)
    rows["rgba"] = (255 << 24) | (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    view = "0 0 0 1 0 0 0"
    if camera is not None:
        view = " ".join(f"{x:.17g}" for x in (*camera.eye, *quaternion(camera.rotation)))
    size = int(dtype[1])
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgba\n"
        f"SIZE {size} {size} {size} 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH {w}\nHEIGHT {h}\n"
        f"VIEWPOINT {view}\nPOINTS {n}\nDATA {data}\n"
    )
    if data == "binary":
        body = rows.tobytes()
    elif data == "ascii":
        fmt = "%.9g" if size == 4 else "%.17g"
        lines = [
            f"{fmt % x} {fmt % y} {fmt % z} {int(v)}"
            for x, y, z, v in zip(rows["x"], rows["y"], rows["z"], rows["rgba"], strict=True)
        ]
        body = ("\n".join(lines) + "\n").encode("ascii")
    elif data == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(rows[f]).tobytes() for f in rows.dtype.names)
        comp = _lzf_literals(raw)
        body = np.array([len(comp), len(raw)], "<u4").tobytes() + comp
    else:
        raise ValueError(f"unknown PCD data {data!r}")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(body)


def _lzf_literals(raw: bytes) -> bytes:
    """An LZF stream of literal runs only (a control byte ``len - 1`` < 32 before each run)."""
    out = bytearray()
    for i in range(0, len(raw), 32):
        chunk = raw[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def true_normals(sdf, points: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Unit gradients of ``sdf`` at ``points`` (n, 3): the scene's outward normals there."""
    g = np.zeros_like(points, dtype=np.float64)
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        g[:, a] = (sdf(points + d) - sdf(points - d)) / (2 * eps)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def exact_image(camera: DepthCamera, sdf) -> np.ndarray:
    """The noise-free organized cloud of ``sdf`` seen by ``camera`` (NaN where nothing is hit)."""
    t = camera.cast(sdf)
    pts = camera.eye + camera.rays() * t[..., None]
    pts[~np.isfinite(t)] = np.nan
    return pts


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return float(w), float(x), float(y), float(z)

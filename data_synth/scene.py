"""Procedural indoor scene: an axis-aligned room seen from inside, with boxes, spheres, cylinders
and slabs, every surface carrying analytic textures.

World frame: metres, z up, the room spans ``ROOM_MIN .. ROOM_MAX`` (4 m x 4 m x 2.6 m). Rays are
``o + t d``; the renderer passes camera-frame directions with ``z = 1`` rotated into the world,
so the ray parameter ``t`` of a hit is its camera-frame depth.

Every primitive offers three vectorised operations:

- ``intersect(rays: Rays) -> (t [M], face [M])``: the first hit in front of the origin
  (``t = inf`` where the ray misses); for the room the exit point of the box (seen from inside).
- ``surface(p [M,3], face [M]) -> (s [M], t [M], n [M,3])``: surface coordinates in metres for the
  textures and the unit normal pointing towards the viewer side.
- ``sdf(p [M,3]) -> [M]``: exact signed distance, positive in free space (outside an object,
  inside the room); ``|sdf|`` is the distance to that primitive's surface.

A scene is fully described by :meth:`Scene.to_dict` (plain JSON numbers); :meth:`Scene.from_dict`
rebuilds it exactly, which is how ``synth.json`` carries it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from data_synth.textures import Texture, evaluate_texture, random_colour_pair, random_texture

ROOM_MIN = (-2.0, -2.0, 0.0)
ROOM_MAX = (2.0, 2.0, 2.6)
# Objects stand in a band along the walls at most this deep, so the camera corridor of every
# trajectory (within 1 m of the room's vertical axis, and the zoom/line paths facing the +x wall)
# keeps at least 0.4 m from any object.
WALL_BAND_M = 0.5
# Sky-like light direction for the view-independent shading 0.75 + 0.25 n.l.
LIGHT_DIRECTION = (0.35, 0.2, 0.915)
_EPS_T = 1e-9


@dataclass(frozen=True)
class SurfaceLayout:
    """Texture of one surface: a base texture and rectangular patches ``(s0, t0, s1, t1)`` on top
    (later patches win where they overlap)."""

    base: Texture
    patches: tuple[tuple[tuple[float, float, float, float], Texture], ...] = ()

    def evaluate(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Albedo.  s [N], t [N] metres -> rgb [N, 3]"""
        rgb = evaluate_texture(self.base, s, t)
        for (s0, t0, s1, t1), texture in self.patches:
            inside = (s >= s0) & (s < s1) & (t >= t0) & (t < t1)
            if inside.any():
                rgb[inside] = evaluate_texture(texture, s[inside], t[inside])
        return rgb

    def to_dict(self) -> dict:
        return {"base": self.base.to_dict(),
                "patches": [{"rect": list(rect), "texture": tex.to_dict()} for rect, tex in self.patches]}

    @staticmethod
    def from_dict(data: Mapping[str, Any]) -> "SurfaceLayout":
        patches = []
        for patch in data.get("patches", []):
            rect = tuple(float(v) for v in patch["rect"])
            if len(rect) != 4:
                raise ValueError(f"patch rect must have 4 numbers (s0, t0, s1, t1), got {patch['rect']}")
            patches.append((rect, Texture.from_dict(patch["texture"])))
        return SurfaceLayout(Texture.from_dict(data["base"]), tuple(patches))


def _safe_inverse(d: np.ndarray) -> np.ndarray:
    """1/d with exact zeros replaced by a huge value of either sign (slab tests stay correct)."""
    return 1.0 / np.where(d == 0.0, 1e-300, d)


class Rays:
    """Rays ``o + t d`` split into contiguous components, with what every primitive reuses.

    o: [M, 3] or [1, 3] (one shared origin broadcasts for free), d: [M, 3]. Components are [M] or [1].
    """

    def __init__(self, o: np.ndarray, d: np.ndarray | None = None, *, components=None):
        if components is None:
            o = np.atleast_2d(np.asarray(o, dtype=np.float64))
            d = np.atleast_2d(np.asarray(d, dtype=np.float64))
            if o.shape[-1] != 3 or d.shape[-1] != 3 or o.shape[0] not in (1, d.shape[0]):
                raise ValueError(f"rays need o [M, 3] or [1, 3] and d [M, 3], got {o.shape} and {d.shape}")
            components = tuple(np.ascontiguousarray(o[:, k]) for k in range(3)) + tuple(
                np.ascontiguousarray(d[:, k]) for k in range(3))
        self.ox, self.oy, self.oz, self.dx, self.dy, self.dz = components
        self.n = self.dx.shape[0]
        self.inv = tuple(_safe_inverse(c) for c in (self.dx, self.dy, self.dz))
        self.dd = self.dx * self.dx + self.dy * self.dy + self.dz * self.dz

    def subset(self, index: np.ndarray) -> "Rays":
        """The rays at ``index`` (an int array).  -> Rays with [len(index)] components"""
        def pick(c: np.ndarray) -> np.ndarray:
            return c if c.shape[0] == 1 else c[index]
        out = Rays.__new__(Rays)
        out.ox, out.oy, out.oz = pick(self.ox), pick(self.oy), pick(self.oz)
        out.dx, out.dy, out.dz = self.dx[index], self.dy[index], self.dz[index]
        out.inv = tuple(c[index] for c in self.inv)
        out.dd = self.dd[index]
        out.n = len(index)
        return out

    def may_hit_sphere(self, centre: Sequence[float], radius: float) -> np.ndarray:
        """Conservative pre-test: the ray's forward half passes within ``radius`` of ``centre``.  -> bool [M]"""
        ox, oy, oz = self.ox - centre[0], self.oy - centre[1], self.oz - centre[2]
        half_b = self.dx * ox + self.dy * oy + self.dz * oz
        c = ox * ox + oy * oy + oz * oz - radius * radius
        # Real roots exist and the far one is ahead (c < 0: origin inside; else half_b < 0: sphere ahead).
        return (half_b * half_b >= self.dd * c) & ((c < 0) | (half_b < 0))


def _nearest_root(half_b: np.ndarray, a: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smaller root of ``a t^2 + 2 half_b t + c = 0`` (stable form) and the discriminant."""
    disc = half_b * half_b - a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    q = -(half_b + np.copysign(root, half_b))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.minimum(q / a, c / q)
    return t, disc


def _yaw_matrix(yaw_deg: float) -> np.ndarray:
    a = math.radians(yaw_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Room:
    """Axis-aligned box seen from inside. Faces: 0 -x wall, 1 +x wall, 2 -y wall, 3 +y wall,
    4 floor, 5 ceiling. Wall coordinates: ``s`` along the wall to the right of a viewer facing it,
    ``t`` height above the floor; floor and ceiling: ``s = x - xmin``, ``t = y - ymin``."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    layouts: tuple[SurfaceLayout, ...]  # 6, one per face

    n_faces = 6

    def intersect(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        best_t = np.full(rays.n, np.inf)
        face = np.zeros(rays.n, dtype=np.int64)
        for axis, (o, d, inv) in enumerate(zip((rays.ox, rays.oy, rays.oz), (rays.dx, rays.dy, rays.dz), rays.inv)):
            positive = d > 0
            t = (np.where(positive, self.hi[axis], self.lo[axis]) - o) * inv
            closer = t < best_t
            best_t = np.where(closer, t, best_t)
            face = np.where(closer, 2 * axis + positive, face)
        return np.where(best_t > _EPS_T, best_t, np.inf), face

    def surface(self, p: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        (x0, y0, z0), (x1, y1, z1) = self.lo, self.hi
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        s = np.select([face == 0, face == 1, face == 2, face == 3], [y - y0, y1 - y, x1 - x, x - x0], x - x0)
        t = np.where(face >= 4, y - y0, z - z0)
        normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
        return s, t, normals[face]

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Distance to the nearest wall, positive inside the room (exact inside)."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        inside = np.minimum(p - lo, hi - p).min(axis=1)
        q = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        return np.where(inside >= 0, inside, -np.linalg.norm(q, axis=1))

    def layout(self, face: int) -> SurfaceLayout:
        return self.layouts[face]

    def to_dict(self) -> dict:
        return {"type": "room", "min": list(self.lo), "max": list(self.hi),
                "faces": [layout.to_dict() for layout in self.layouts]}


@dataclass(frozen=True)
class Box:
    """Box with half sizes ``half`` (local x, y, z), rotated by ``yaw`` degrees about world z.
    Faces 0..5 = local -x, +x, -y, +y, -z, +z. Slabs (shelves, boards) are thin boxes."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    texture: SurfaceLayout
    kind: str = "box"  # "box" or "slab" (same geometry, a name for the reader of synth.json)

    n_faces = 6

    def _to_local(self, p: np.ndarray) -> np.ndarray:
        """World points to the box frame, R^T (p - c).  p [M, 3] -> [M, 3]"""
        a = math.radians(self.yaw)
        ca, sa = math.cos(a), math.sin(a)
        x, y, z = p[:, 0] - self.center[0], p[:, 1] - self.center[1], p[:, 2] - self.center[2]
        return np.stack([ca * x + sa * y, -sa * x + ca * y, z], axis=1)

    def intersect(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        a = math.radians(self.yaw)
        ca, sa = math.cos(a), math.sin(a)
        cx, cy, cz = self.center
        ox, oy = rays.ox - cx, rays.oy - cy
        # Local frame: R^T applied to origin and direction (rotation about z only).
        o_local = (ca * ox + sa * oy, -sa * ox + ca * oy, rays.oz - cz)
        d_local = (ca * rays.dx + sa * rays.dy, -sa * rays.dx + ca * rays.dy, rays.dz)
        inv_local = (_safe_inverse(d_local[0]), _safe_inverse(d_local[1]), rays.inv[2])
        t_near = np.full(rays.n, -np.inf)
        t_far = np.full(rays.n, np.inf)
        face = np.zeros(rays.n, dtype=np.int64)
        for axis in range(3):
            h, o, d, inv = self.half[axis], o_local[axis], d_local[axis], inv_local[axis]
            t_lo = (-h - o) * inv
            t_hi = (h - o) * inv
            entry = np.minimum(t_lo, t_hi)
            later = entry > t_near
            t_near = np.where(later, entry, t_near)
            face = np.where(later, 2 * axis + (d < 0), face)  # entering through the + face when d < 0
            t_far = np.minimum(t_far, np.maximum(t_lo, t_hi))
        hit = (t_near <= t_far) & (t_near > _EPS_T)
        return np.where(hit, t_near, np.inf), face

    def surface(self, p: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = self._to_local(p)
        hx, hy, hz = self.half
        x, y, z = q[:, 0], q[:, 1], q[:, 2]
        s = np.select([face == 0, face == 1, face == 2, face == 3], [y + hy, hy - y, hx - x, x + hx], x + hx)
        t = np.where(face >= 4, y + hy, z + hz)
        local_normals = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)
        return s, t, local_normals[face] @ _yaw_matrix(self.yaw).T

    def bounding_sphere(self) -> tuple[tuple[float, float, float], float]:
        return self.center, math.sqrt(sum(h * h for h in self.half)) * (1 + 1e-9) + 1e-9

    def sdf(self, p: np.ndarray) -> np.ndarray:
        q = np.abs(self._to_local(p)) - np.asarray(self.half)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside

    def layout(self, face: int) -> SurfaceLayout:
        return self.texture

    def to_dict(self) -> dict:
        return {"type": self.kind, "center": list(self.center), "half": list(self.half), "yaw": self.yaw,
                "texture": self.texture.to_dict()}


@dataclass(frozen=True)
class Sphere:
    """Sphere; texture coordinates ``s = r * azimuth``, ``t = r * elevation`` (arc lengths)."""

    center: tuple[float, float, float]
    radius: float
    texture: SurfaceLayout

    n_faces = 1

    def intersect(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        ox, oy, oz = rays.ox - self.center[0], rays.oy - self.center[1], rays.oz - self.center[2]
        half_b = rays.dx * ox + rays.dy * oy + rays.dz * oz
        c = ox * ox + oy * oy + oz * oz - self.radius**2
        t, disc = _nearest_root(half_b, rays.dd, c)
        hit = (disc >= 0) & (t > _EPS_T)
        return np.where(hit, t, np.inf), np.zeros(rays.n, dtype=np.int64)

    def surface(self, p: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v = p - np.asarray(self.center)
        r = self.radius
        s = r * np.arctan2(v[:, 1], v[:, 0])
        t = r * np.arcsin(np.clip(v[:, 2] / r, -1.0, 1.0))
        return s, t, v / r

    def bounding_sphere(self) -> tuple[tuple[float, float, float], float]:
        return self.center, self.radius * (1 + 1e-9) + 1e-9

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p - np.asarray(self.center), axis=1) - self.radius

    def layout(self, face: int) -> SurfaceLayout:
        return self.texture

    def to_dict(self) -> dict:
        return {"type": "sphere", "center": list(self.center), "radius": self.radius,
                "texture": self.texture.to_dict()}


@dataclass(frozen=True)
class Cylinder:
    """Vertical capped cylinder over ``z0 .. z1``. Faces: 0 side (``s = r * azimuth``,
    ``t = z - z0``), 1 bottom cap, 2 top cap (``s, t`` = x, y relative to the axis)."""

    center_xy: tuple[float, float]
    z0: float
    z1: float
    radius: float
    texture: SurfaceLayout

    n_faces = 3

    def intersect(self, rays: Rays) -> tuple[np.ndarray, np.ndarray]:
        cx, cy = self.center_xy
        ox, oy, oz = rays.ox - cx, rays.oy - cy, rays.oz
        dx, dy, dz = rays.dx, rays.dy, rays.dz
        a = dx * dx + dy * dy
        half_b = dx * ox + dy * oy
        c = ox * ox + oy * oy - self.radius**2
        t_side, disc = _nearest_root(half_b, a, c)
        z_side = oz + t_side * dz
        side_ok = (disc >= 0) & (a > 0) & (t_side > _EPS_T) & (z_side >= self.z0) & (z_side <= self.z1)
        best_t = np.where(side_ok, t_side, np.inf)
        best_face = np.zeros(rays.n, dtype=np.int64)
        for face, z_cap in ((1, self.z0), (2, self.z1)):
            t_cap = (z_cap - oz) * rays.inv[2]
            px, py = ox + t_cap * dx, oy + t_cap * dy
            ok = (t_cap > _EPS_T) & (px * px + py * py <= self.radius**2) & (t_cap < best_t)
            best_t = np.where(ok, t_cap, best_t)
            best_face = np.where(ok, face, best_face)
        return best_t, best_face

    def surface(self, p: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cx, cy = self.center_xy
        vx, vy = p[:, 0] - cx, p[:, 1] - cy
        side = face == 0
        s = np.where(side, self.radius * np.arctan2(vy, vx), vx)
        t = np.where(side, p[:, 2] - self.z0, vy)
        n = np.zeros_like(p)
        n[:, 0] = np.where(side, vx / self.radius, 0.0)
        n[:, 1] = np.where(side, vy / self.radius, 0.0)
        n[:, 2] = np.select([face == 1, face == 2], [-1.0, 1.0], 0.0)
        return s, t, n

    def bounding_sphere(self) -> tuple[tuple[float, float, float], float]:
        half_height = 0.5 * (self.z1 - self.z0)
        centre = (self.center_xy[0], self.center_xy[1], 0.5 * (self.z0 + self.z1))
        return centre, math.hypot(self.radius, half_height) * (1 + 1e-9) + 1e-9

    def sdf(self, p: np.ndarray) -> np.ndarray:
        cx, cy = self.center_xy
        radial = np.hypot(p[:, 0] - cx, p[:, 1] - cy) - self.radius
        axial = np.abs(p[:, 2] - 0.5 * (self.z0 + self.z1)) - 0.5 * (self.z1 - self.z0)
        outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
        inside = np.minimum(np.maximum(radial, axial), 0.0)
        return outside + inside

    def layout(self, face: int) -> SurfaceLayout:
        return self.texture

    def to_dict(self) -> dict:
        return {"type": "cylinder", "center_xy": list(self.center_xy), "z0": self.z0, "z1": self.z1,
                "radius": self.radius, "texture": self.texture.to_dict()}


Primitive = Room | Box | Sphere | Cylinder


@dataclass(frozen=True)
class Scene:
    """The room (primitive 0) and its objects (primitives 1..)."""

    room: Room
    objects: tuple[Box | Sphere | Cylinder, ...]
    seed: int
    light: tuple[float, float, float] = LIGHT_DIRECTION

    @property
    def primitives(self) -> tuple[Primitive, ...]:
        return (self.room, *self.objects)

    # ------------------------------------------------------------------ ray casting
    def trace(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit of each ray ``o + t d``.  o [M,3] or [1,3] (shared origin), d [M,3] ->
        (t [M], primitive index [M], face [M]); ``t = inf`` and index -1 where nothing is hit
        (only possible from outside the room). With ``d_z = 1`` in the camera frame t is the depth."""
        return self.trace_rays(Rays(o, d))

    def trace_rays(self, rays: Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`trace` on prepared :class:`Rays`; objects are tested only on the rays that pass
        their bounding sphere."""
        best_t, best_face = self.room.intersect(rays)
        best_prim = np.where(np.isfinite(best_t), 0, -1)
        for index, obj in enumerate(self.objects, start=1):
            centre, radius = obj.bounding_sphere()
            candidates = np.flatnonzero(rays.may_hit_sphere(centre, radius))
            if candidates.size == 0:
                continue
            t, face = obj.intersect(rays.subset(candidates))
            closer = t < best_t[candidates]
            rows = candidates[closer]
            best_t[rows] = t[closer]
            best_prim[rows] = index
            best_face[rows] = face[closer]
        return best_t, best_prim, best_face

    def radiance(self, p: np.ndarray, primitive: np.ndarray, face: np.ndarray) -> np.ndarray:
        """View-independent radiance at hit points: albedo * (0.75 + 0.25 n.l).
        p [M,3], primitive [M], face [M] -> rgb [M,3] (black where primitive is -1)."""
        rgb = np.zeros((len(p), 3))
        light = np.asarray(self.light) / np.linalg.norm(self.light)
        for index, prim in enumerate(self.primitives):
            rows = np.flatnonzero(primitive == index)
            if rows.size == 0:
                continue
            s, t, n = prim.surface(p[rows], face[rows])
            albedo = np.empty((rows.size, 3))
            faces_here = face[rows]
            for f in np.unique(faces_here):
                sel = faces_here == f
                albedo[sel] = prim.layout(int(f)).evaluate(s[sel], t[sel])
            rgb[rows] = albedo * (0.75 + 0.25 * (n @ light))[:, None]
        return rgb

    # ------------------------------------------------------------------ distances
    def surface_distance(self, p: np.ndarray) -> np.ndarray:
        """Distance to the nearest primitive surface (room walls included).  p [M,3] -> [M] metres"""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        return np.min([np.abs(prim.sdf(p)) for prim in self.primitives], axis=0)

    def clearance(self, p: np.ndarray) -> np.ndarray:
        """Signed free-space distance: positive inside the room and outside every object.  p [M,3] -> [M]"""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        return np.min([self.room.sdf(p), *[obj.sdf(p) for obj in self.objects]], axis=0)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        return {"seed": self.seed, "units": "metres", "up_axis": "z", "light_direction": list(self.light),
                "shading": "albedo * (0.75 + 0.25 * dot(normal, normalize(light_direction)))",
                "room": self.room.to_dict(), "objects": [obj.to_dict() for obj in self.objects]}

    @staticmethod
    def from_dict(data: Mapping[str, Any]) -> "Scene":
        """Rebuild exactly from :meth:`to_dict`; raises KeyError/ValueError/TypeError on bad input."""
        room_d = data["room"]
        faces = room_d["faces"]
        if len(faces) != 6:
            raise ValueError(f"room needs 6 face layouts, got {len(faces)}")
        room = Room(_vec(room_d["min"], 3), _vec(room_d["max"], 3), tuple(SurfaceLayout.from_dict(f) for f in faces))
        objects: list[Box | Sphere | Cylinder] = []
        for obj in data["objects"]:
            kind = obj.get("type")
            texture = SurfaceLayout.from_dict(obj["texture"])
            if kind in ("box", "slab"):
                objects.append(Box(_vec(obj["center"], 3), _vec(obj["half"], 3), float(obj["yaw"]), texture, kind))
            elif kind == "sphere":
                objects.append(Sphere(_vec(obj["center"], 3), float(obj["radius"]), texture))
            elif kind == "cylinder":
                objects.append(Cylinder(_vec(obj["center_xy"], 2), float(obj["z0"]), float(obj["z1"]),
                                        float(obj["radius"]), texture))
            else:
                raise ValueError(f"unknown object type {kind!r} (known: box, slab, sphere, cylinder)")
        light = _vec(data.get("light_direction", LIGHT_DIRECTION), 3)
        return Scene(room, tuple(objects), int(data["seed"]), light)


def _vec(values: Sequence[float], n: int) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise ValueError(f"expected {n} finite numbers, got {values!r}")
    return out


# ----------------------------------------------------------------------------- procedural scene
def _rounded(x: float) -> float:
    return round(float(x), 6)


def _layout(base: Texture, patches: list[tuple[tuple[float, float, float, float], Texture]]) -> SurfaceLayout:
    return SurfaceLayout(base, tuple((tuple(_rounded(v) for v in rect), tex) for rect, tex in patches))


def _feature_wall(rng: np.random.Generator) -> SurfaceLayout:
    """The +x wall, faced by the zoom, line and static trajectories: a test chart in the centre
    (fine print, fine checker, blinds, rotated checker in shuffled quadrants, s in [1.5, 2.5],
    t in [0.95, 1.65]) surrounded by blinds, a checker ladder at three frequencies, print and a
    smooth panel."""
    chart = [random_texture(rng, "print", fine=True), random_texture(rng, "checker", fine=True),
             random_texture(rng, "stripes", fine=True), random_texture(rng, "checker", fine=True)]
    rotated = chart[3].params | {"angle": _rounded(rng.uniform(20, 40))}
    chart[3] = Texture("checker", rotated)
    order = rng.permutation(4)
    quadrants = [(1.5, 1.3, 2.0, 1.65), (2.0, 1.3, 2.5, 1.65), (1.5, 0.95, 2.0, 1.3), (2.0, 0.95, 2.5, 1.3)]
    patches = [(quadrants[q], chart[i]) for q, i in zip(range(4), order)]
    blinds = random_texture(rng, "stripes")
    blinds = Texture("stripes", blinds.params | {"angle": 90.0, "period": _rounded(rng.uniform(0.02, 0.035))})
    patches.append(((0.15, 0.5, 1.35, 2.3), blinds))
    ladder_periods = (_rounded(rng.uniform(0.08, 0.14)), _rounded(rng.uniform(0.025, 0.04)), _rounded(rng.uniform(0.006, 0.012)))
    c0, c1 = random_colour_pair(rng)
    for (t0, t1), period in zip(((1.7, 2.3), (1.1, 1.7), (0.5, 1.1)), ladder_periods):
        patches.append(((2.65, t0, 3.85, t1), Texture("checker", {"c0": c0, "c1": c1, "period": period, "angle": 0.0})))
    patches.append(((1.5, 0.2, 2.5, 0.85), random_texture(rng, "print")))
    patches.append(((1.5, 1.75, 2.5, 2.45), random_texture(rng, "smooth")))
    return _layout(random_texture(rng, "smooth"), patches)


def _patchwork(rng: np.random.Generator, width: float, height: float, columns: int, rows: int,
               fill: float, kinds: Sequence[str]) -> SurfaceLayout:
    """A smooth base with random patches in a ``columns x rows`` grid of cells."""
    patches = []
    cell_w, cell_h = width / columns, height / rows
    for row in range(rows):
        for col in range(columns):
            if rng.uniform() > fill:
                continue
            margin_s = rng.uniform(0.04, 0.2) * cell_w
            margin_t = rng.uniform(0.04, 0.2) * cell_h
            kind = str(rng.choice(list(kinds)))
            rect = (col * cell_w + margin_s, row * cell_h + margin_t, (col + 1) * cell_w - margin_s, (row + 1) * cell_h - margin_t)
            patches.append((rect, random_texture(rng, kind, fine=bool(rng.uniform() < 0.3))))
    return _layout(random_texture(rng, "smooth"), patches)


def _wall_frame(wall: str) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Inward normal, tangent, the wall's foot point on the room's mid-line, and its yaw (degrees)
    such that local +x of a box with that yaw points along the inward normal."""
    lo, hi = ROOM_MIN, ROOM_MAX
    table = {
        "-x": ((1.0, 0.0), (0.0, 1.0), (lo[0], 0.0), 0.0),
        "+x": ((-1.0, 0.0), (0.0, -1.0), (hi[0], 0.0), 180.0),
        "-y": ((0.0, 1.0), (-1.0, 0.0), (0.0, lo[1]), 90.0),
        "+y": ((0.0, -1.0), (1.0, 0.0), (0.0, hi[1]), -90.0),
    }
    n, tan, foot, yaw = table[wall]
    return np.array(n), np.array(tan), np.array(foot), yaw


def _random_object(rng: np.random.Generator) -> dict:
    """Draw one object: a wall, a position along it and a shape fitting the wall band."""
    kind = str(rng.choice(["box", "box", "sphere", "cylinder", "slab"]))
    wall = str(rng.choice(["-x", "+y", "-y", "+x"]))
    n, tan, foot, wall_yaw = _wall_frame(wall)
    texture_kind = str(rng.choice(["stripes", "checker", "print", "smooth", "checker"]))
    texture = SurfaceLayout(random_texture(rng, texture_kind, fine=bool(rng.uniform() < 0.3)))
    if kind in ("box", "slab"):
        yaw_jitter = float(rng.uniform(-8, 8)) if kind == "box" else 0.0
        if kind == "box":
            half = (rng.uniform(0.1, 0.17), rng.uniform(0.15, 0.35), rng.uniform(0.25, 0.7))
            z_center = half[2]
            gap = rng.uniform(0.0, 0.03)
        else:  # a shelf board fixed to the wall
            half = (rng.uniform(0.08, 0.14), rng.uniform(0.25, 0.5), rng.uniform(0.012, 0.025))
            z_center = rng.uniform(0.8, 1.9)
            gap = 0.0
        a = math.radians(yaw_jitter)
        extent_n = half[0] * abs(math.cos(a)) + half[1] * abs(math.sin(a))
        extent_t = half[0] * abs(math.sin(a)) + half[1] * abs(math.cos(a))
        z_range = (z_center - half[2], z_center + half[2])
        shape = {"type": kind, "half": [_rounded(h) for h in half], "yaw": _rounded(wall_yaw + yaw_jitter)}
    elif kind == "sphere":
        radius = rng.uniform(0.1, 0.22)
        extent_n = extent_t = radius
        gap = rng.uniform(0.02, 0.05)
        z_center = radius if rng.uniform() < 0.4 else rng.uniform(0.6, 2.0)
        z_range = (z_center - radius, z_center + radius)
        shape = {"type": "sphere", "radius": _rounded(radius)}
    else:
        radius = rng.uniform(0.08, 0.2)
        extent_n = extent_t = radius
        gap = rng.uniform(0.02, 0.06)
        z_range = (0.0, rng.uniform(0.5, 1.8))
        shape = {"type": "cylinder", "radius": _rounded(radius), "z0": 0.0, "z1": _rounded(z_range[1])}
    # Position along the wall: anywhere on the side walls; only the corners of the +x (feature) wall.
    limit = 1.9 - extent_t
    if wall == "+x":
        u = float(rng.uniform(1.15 + extent_t, limit)) * float(rng.choice([-1.0, 1.0])) if limit > 1.15 + extent_t else None
    else:
        u = float(rng.uniform(-limit, limit))
    depth = gap + extent_n
    center_xy = foot + n * depth + tan * (u if u is not None else 0.0)
    return {"shape": shape, "center_xy": center_xy, "z_range": z_range, "extent": math.hypot(extent_n, extent_t),
            "z_center": z_center if kind != "cylinder" else None, "texture": texture, "valid": u is not None,
            "band_ok": depth + extent_n <= WALL_BAND_M}


def make_scene(seed: int, *, n_objects: int | None = None) -> Scene:
    """The procedural room for ``seed`` (deterministic): textured walls, floor and ceiling, and
    ``n_objects`` (default 7..9) boxes, slabs, spheres and cylinders standing in the wall band."""
    rng = np.random.default_rng([int(seed), 0x5CE4E])
    width_x = ROOM_MAX[0] - ROOM_MIN[0]
    width_y = ROOM_MAX[1] - ROOM_MIN[1]
    height = ROOM_MAX[2] - ROOM_MIN[2]
    wall_kinds = ("stripes", "checker", "print", "smooth", "checker")
    faces = [
        _patchwork(rng, width_y, height, 4, 2, 0.7, wall_kinds),   # -x
        _feature_wall(rng),                                         # +x
        _patchwork(rng, width_x, height, 4, 2, 0.7, wall_kinds),   # -y
        _patchwork(rng, width_x, height, 4, 2, 0.7, wall_kinds),   # +y
    ]
    floor_c0, floor_c1 = random_colour_pair(rng)
    floor_base = Texture("checker", {"c0": floor_c0, "c1": floor_c1, "period": _rounded(rng.uniform(0.25, 0.45)),
                                     "angle": 0.0})
    floor_rug = random_texture(rng, str(rng.choice(["stripes", "checker"])), fine=True)
    faces.append(_layout(floor_base, [((1.0, 1.0, 3.0, 3.0), floor_rug)]))
    faces.append(_patchwork(rng, width_x, width_y, 2, 2, 0.5, ("stripes", "smooth", "checker")))
    room = Room(ROOM_MIN, ROOM_MAX, tuple(faces))

    count = int(rng.integers(7, 10)) if n_objects is None else int(n_objects)
    placed: list[dict] = []
    attempts = 0
    while len(placed) < count and attempts < 400:
        attempts += 1
        candidate = _random_object(rng)
        if not (candidate["valid"] and candidate["band_ok"]):
            continue
        clash = False
        for other in placed:
            z_overlap = candidate["z_range"][0] < other["z_range"][1] + 0.02 and other["z_range"][0] < candidate["z_range"][1] + 0.02
            near = np.linalg.norm(candidate["center_xy"] - other["center_xy"]) < candidate["extent"] + other["extent"] + 0.03
            if z_overlap and near:
                clash = True
                break
        if not clash:
            placed.append(candidate)
    objects: list[Box | Sphere | Cylinder] = []
    for item in placed:
        shape = item["shape"]
        cx, cy = (_rounded(v) for v in item["center_xy"])
        if shape["type"] in ("box", "slab"):
            objects.append(Box((cx, cy, _rounded(item["z_center"])), tuple(shape["half"]), shape["yaw"], item["texture"], shape["type"]))
        elif shape["type"] == "sphere":
            objects.append(Sphere((cx, cy, _rounded(item["z_center"])), shape["radius"], item["texture"]))
        else:
            objects.append(Cylinder((cx, cy), shape["z0"], shape["z1"], shape["radius"], item["texture"]))
    return Scene(room, tuple(objects), int(seed))

"""Host-side ModelBuilder: collects cloth meshes, materials, handles and scene forces, then finalises a Model."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpcloth import mesh_io
from warpcloth.geometry.primitives import box_mesh, contact_edges, funnel_mesh, plane_mesh, sphere_mesh, unique_edges
from warpcloth.geometry.transforms import placement
from warpcloth.lookup import fold_direction, stretching_lut
from warpcloth.materials import Material
from warpcloth.model import CollisionSettings, Model, Motion
from warpcloth.obstacles import Obstacle, RigidMotion

DEFAULT_HANDLE_STIFFNESS = 1.0e3
"""ARCSim's ``magic.handle_stiffness`` [N/m]."""

# Collision defaults: the seed's BVH thickness [m]; ARCSim's repulsion thickness [m], collision_stiffness [N/m^3]
# and cloth-cloth and cloth-obstacle friction coefficients (SPEC §1.4).
DEFAULT_COLLISION_THICKNESS = 5.0e-4
DEFAULT_REPULSION_THICKNESS = 5.0e-3
DEFAULT_REPULSION_STIFFNESS = 1.0e6
DEFAULT_FRICTION = 0.6
DEFAULT_OBSTACLE_FRICTION = 0.3


def _finite_vector(name: str, value, length: int = 3) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (length,):
        raise ValueError(f"{name} must have {length} components, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has a non-finite component: {arr.tolist()}")
    return arr


def _motion(name: str, motion) -> Motion | None:
    if motion is None:
        return None
    keys = list(motion)
    if not keys:
        raise ValueError(f"{name}: motion needs at least one (time, offset) keyframe")
    times = np.array([float(k[0]) for k in keys])
    offsets = np.array([_finite_vector(f"{name} motion offset {i}", k[1]) for i, k in enumerate(keys)])
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0.0):
        raise ValueError(f"{name}: motion key times must be finite and strictly increasing, got {times.tolist()}")
    return Motion(times, offsets)


def _local_frame_uv(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Material coordinates for meshes without ``vt``: each triangle in its own 2D frame (rest = initial shape)."""
    x0, x1, x2 = (positions[triangles[:, c]] for c in range(3))
    e1, e2 = x1 - x0, x2 - x0
    l1 = np.linalg.norm(e1, axis=1)
    n = np.cross(e1, e2)
    nn = np.linalg.norm(n, axis=1)
    bad = np.flatnonzero((l1 <= 0.0) | (nn <= 1e-300))
    if bad.size:
        t = int(bad[0])
        raise ValueError(f"triangle {t} {triangles[t].tolist()} is degenerate (zero area) in its initial shape")
    u = e1 / l1[:, None]
    v = np.cross(n / nn[:, None], u)
    uv = np.zeros((len(triangles), 3, 2))
    uv[:, 1, 0] = l1
    uv[:, 2, 0] = np.einsum("ij,ij->i", e2, u)
    uv[:, 2, 1] = np.einsum("ij,ij->i", e2, v)
    return uv


@dataclass(frozen=True)
class _World:
    first_particle: int
    first_obstacle: int
    gravity: np.ndarray
    wind: tuple[np.ndarray, float, float] | None
    # scene-wide: every world of a model has the same
    shared: tuple


class ModelBuilder:
    """Collects a scene on the host (NumPy) and ``finalize``s it into a device ``Model``.

    Example:
        >>> b = ModelBuilder()
        >>> b.add_cloth_grid((16, 16), (1.0, 1.0), material=preset("gray-interlock"))
        >>> model = b.finalize(device="cpu", requires_grad=True)"""

    max_particles: int = 4_000_000
    """Most particles a model may have; more raises ValueError before anything is allocated. An instance may raise
    it. Why: docs/decisions.md, 'A particle limit before allocation'."""
    BYTES_PER_PARTICLE = 6000
    """Peak memory [bytes] per particle of building and stepping a model with gradients: the error's estimate."""

    def __init__(self, *, gravity: Sequence[float] = (0.0, 0.0, -9.8)):
        self.gravity = _finite_vector("gravity", gravity)
        self._positions: list[np.ndarray] = []
        self._velocities: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._tri_uv: list[np.ndarray] = []
        self._tri_material: list[np.ndarray] = []
        self._rest_angle_initial: list[bool] = []
        self._materials: list[Material] = []
        self._particle_count = 0
        self._handles: list[tuple[int, float, Motion | None, tuple[float, float] | None]] = []
        self._grippers: list = []  # warpcloth.grippers.Gripper, in the order added
        self._pins: list[tuple[int, Motion | None]] = []
        self.wind: tuple[np.ndarray, float, float] | None = None
        self.wind_lagged_normals = False
        self.damping_mass = 0.0
        self.damping_stiffness = 0.0
        self._obstacles: list[Obstacle] = []
        self.self_collision = False
        self.collision_thickness = DEFAULT_COLLISION_THICKNESS
        self.repulsion = (DEFAULT_REPULSION_THICKNESS, DEFAULT_REPULSION_STIFFNESS, DEFAULT_FRICTION,
                          DEFAULT_OBSTACLE_FRICTION)
        self._worlds: list[_World] = []  # empty: the builder's own scene is the model's one world

    @property
    def particle_count(self) -> int:
        return self._particle_count

    @property
    def obstacle_count(self) -> int:
        return len(self._obstacles)

    @property
    def obstacles(self) -> tuple[Obstacle, ...]:
        """The obstacles added so far (validated), in index order."""
        return tuple(self._obstacles)

    # -- worlds ------------------------------------------------------------------------------------------------------
    def add_world(self, builder: ModelBuilder, *, own_materials: bool = False) -> int:
        """Add a copy of ``builder`` as a new, non-interacting world; returns its index. Damping, collision settings
        and lagged normals must match other worlds'. Obstacles become ``<name>_<world>``; materials are shared unless
        ``own_materials``.

        Raises:
            ValueError: this builder has a scene of its own, ``builder`` has no cloth, or a scene-wide setting
                differs from the worlds added before (naming it)."""
        if not isinstance(builder, ModelBuilder):
            raise TypeError(f"add_world: expected a ModelBuilder, got {type(builder).__name__}")
        if builder is self:
            raise ValueError("add_world: a builder cannot add itself as a world")
        if not self._worlds:
            own = "a cloth" if self._particle_count else "obstacles" if self._obstacles else None
            changed = self.wind is not None or self._own_world().shared != ModelBuilder()._own_world().shared
            if own is None and changed:
                own = "wind, damping or collision settings (set them on each world's builder)"
            if own is not None:
                raise ValueError(f"add_world: this builder has {own} of its own; a builder holds either its own "
                                 "scene or worlds added with add_world/replicate")
        if builder.particle_count == 0:
            raise ValueError("add_world: the builder has no cloth")
        self._check_size(builder.particle_count, f"world {len(self._worlds)}")
        sources = builder._worlds or [builder._own_world()]
        for source in sources:
            if self._worlds and source.shared != self._worlds[0].shared:
                names = ("damping mass", "damping stiffness", "self_collision", "collision thickness",
                         "repulsion (thickness, stiffness, friction, obstacle friction)", "wind lagged_normals")
                which = [f"{n} {a} (world 0: {b})" for n, a, b in zip(names, source.shared, self._worlds[0].shared)
                         if a != b]
                raise ValueError(f"add_world: world {len(self._worlds)} differs from world 0 in a scene-wide "
                                 f"setting, which every world of a model shares: {'; '.join(which)}")
            self._worlds.append(dataclasses.replace(source, first_particle=self._particle_count + source.first_particle,
                                                    first_obstacle=len(self._obstacles) + source.first_obstacle))
        first_world = len(self._worlds) - len(sources)
        offset = self._particle_count
        materials = [self.add_material(m.copy() if own_materials else m) for m in builder._materials]
        self._positions += [p.copy() for p in builder._positions]
        self._velocities += [v.copy() for v in builder._velocities]
        self._triangles += [t + offset for t in builder._triangles]
        self._tri_uv += [uv.copy() for uv in builder._tri_uv]
        self._tri_material += [np.asarray(materials, dtype=np.int32)[m] for m in builder._tri_material]
        self._rest_angle_initial += builder._rest_angle_initial
        self._handles += [(p + offset, k, motion, window) for p, k, motion, window in builder._handles]
        self._grippers += [dataclasses.replace(g, particles=tuple(p + offset for p in g.particles))
                           for g in builder._grippers]
        self._pins += [(p + offset, motion) for p, motion in builder._pins]
        starts = [s.first_obstacle for s in sources] + [len(builder._obstacles)]
        for w in range(len(sources)):
            for o in builder._obstacles[starts[w]:starts[w + 1]]:
                self._obstacles.append(dataclasses.replace(o, name=f"{o.name}_{first_world + w}"))
        self._particle_count += builder.particle_count
        return len(self._worlds) - 1

    def replicate(self, builder: ModelBuilder, count: int, *, own_materials: bool = False) -> range:
        """Add ``count`` copies of ``builder`` as worlds (:meth:`add_world`); returns their world indices."""
        if not _is_integer(count) or count < 1:
            raise ValueError(f"replicate: count must be a positive integer, got {count!r}")
        self._check_size(builder.particle_count * int(count), f"{count} worlds")
        first = len(self._worlds)
        for _ in range(int(count)):
            self.add_world(builder, own_materials=own_materials)
        return range(first, len(self._worlds))

    @property
    def world_count(self) -> int:
        """Worlds of the model this builder makes: those added with add_world/replicate, or 1 (its own scene)."""
        return len(self._worlds) or 1

    def _own_world(self) -> _World:
        shared = (self.damping_mass, self.damping_stiffness, self.self_collision, self.collision_thickness,
                  self.repulsion, self.wind_lagged_normals)
        wind = None if self.wind is None else (self.wind[0].copy(), self.wind[1], self.wind[2])
        return _World(0, 0, self.gravity.copy(), wind, shared)

    def _check_own(self, what: str) -> None:
        if self._worlds:
            raise ValueError(f"{what}: this builder holds worlds added with add_world/replicate; add it to the "
                             "world's own builder before adding the world")

    # -- cloth -----------------------------------------------------------------------------------------------------
    def add_material(self, material: Material) -> int:
        """Register a material (validated) and return its index; the same object is registered once."""
        if not isinstance(material, Material):
            hint = f" (for a preset: warpcloth.preset({material!r}))" if isinstance(material, str) else ""
            raise TypeError(f"material must be a warpcloth.Material, got {type(material).__name__} {material!r}{hint}")
        for i, m in enumerate(self._materials):
            if m is material:
                return i
        material.validate()
        self._materials.append(material)
        return len(self._materials) - 1

    def add_cloth_mesh(
        self,
        mesh: mesh_io.TriangleMesh,
        *,
        material: Material,
        vel: Sequence[float] | None = None,
        rest_angle: str = "flat",
    ) -> int:
        """Add a cloth of ``material`` from a triangle mesh; returns the index of its first particle.

        Without ``mesh.tri_uv`` [m] each triangle rests in its initial shape. ``vel`` [m/s]: default the mesh's, else
        zero. ``rest_angle``: ``"flat"`` (ARCSim's) or ``"initial"`` (the initial shape's dihedral angles).

        Raises:
            ValueError: an invalid mesh or ``rest_angle``, a vertex in no triangle, a non-finite velocity, or more
                than ``max_particles``."""
        self._check_own("add_cloth_mesh")
        if rest_angle not in ("flat", "initial"):
            raise ValueError(f"rest_angle must be 'flat' or 'initial', got {rest_angle!r}")
        positions = np.asarray(mesh.positions, dtype=np.float64)
        triangles = np.asarray(mesh.triangles, dtype=np.int64)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"mesh positions must have shape (N, 3), got {positions.shape}")
        self._check_size(len(positions), f"a cloth mesh of {len(positions):,} vertices")
        if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
            raise ValueError(f"mesh triangles must have shape (T, 3) with T > 0, got {triangles.shape}")
        tri_uv = None if mesh.tri_uv is None else np.asarray(mesh.tri_uv, dtype=np.float64)
        mesh_io.validate_triangles(positions, triangles, tri_uv)
        unused = np.setdiff1d(np.arange(len(positions)), triangles)
        if unused.size:  # it would get no mass and hang frozen in mid-air
            v = int(unused[0])
            raise ValueError(f"cloth vertex {v} at {positions[v].tolist()} is in no triangle ({unused.size} such "
                             "vertices); remove unused vertices from the mesh")
        if tri_uv is None:
            tri_uv = _local_frame_uv(positions, triangles)
        if vel is not None:
            velocities = np.tile(_finite_vector("vel", vel), (len(positions), 1))
        elif getattr(mesh, "velocities", None) is not None:
            velocities = np.asarray(mesh.velocities, dtype=np.float64).reshape(len(positions), 3)
            bad = np.flatnonzero(~np.all(np.isfinite(velocities), axis=1))
            if bad.size:
                raise ValueError(f"vertex {int(bad[0])} has a non-finite velocity {velocities[bad[0]].tolist()}")
        else:
            velocities = np.zeros((len(positions), 3))
        mat = self.add_material(material)
        self._positions.append(positions)
        self._velocities.append(velocities)
        self._triangles.append(triangles + self._particle_count)
        self._tri_uv.append(tri_uv)
        self._tri_material.append(np.full(len(triangles), mat, dtype=np.int32))
        self._rest_angle_initial.append(rest_angle == "initial")
        first = self._particle_count
        self._particle_count += len(positions)
        return first

    def add_cloth_grid(
        self,
        res: Sequence[int],
        size: Sequence[float],
        *,
        material: Material,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        rot: np.ndarray | None = None,
        vel: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> int:
        """Add a flat cloth of ``res`` = (cells_x, cells_y) cells and ``size`` = (width, height) [m]: the
        :func:`~warpcloth.grid_mesh` rotated by ``rot`` (3x3), then translated by ``pos`` [m]."""
        res = tuple(res)
        if len(res) != 2 or not all(_is_integer(r) and r >= 1 for r in res):
            raise ValueError(f"res must be two positive cell counts, got {res}")
        res = (int(res[0]), int(res[1]))
        self._check_size((res[0] + 1) * (res[1] + 1), f"a grid of {res[0]}x{res[1]} cells")
        size = _finite_vector("size", size, 2)
        if np.any(size <= 0.0):
            raise ValueError(f"size must be positive, got {size.tolist()}")
        mesh = mesh_io.grid_mesh(res[0], res[1], float(size[0]), float(size[1]))
        R = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise ValueError("rot must be a 3x3 rotation matrix")
        mesh.positions = mesh.positions @ R.T + _finite_vector("pos", pos)
        return self.add_cloth_mesh(mesh, material=material, vel=vel)

    def add_cloth_obj(
        self,
        path,
        *,
        material: Material,
        scale: float = 1.0,
        rot: np.ndarray | None = None,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        vel: Sequence[float] | None = None,
    ) -> int:
        """Add a cloth from an OBJ file (``vt``: material coordinates): scaled, rotated, then translated."""
        mesh = mesh_io.load_obj(path, scale=scale)
        if rot is not None:
            mesh.positions = mesh.positions @ np.asarray(rot, dtype=np.float64).T
            if mesh.velocities is not None:
                mesh.velocities = mesh.velocities @ np.asarray(rot, dtype=np.float64).T
        mesh.positions = mesh.positions + _finite_vector("pos", pos)
        return self.add_cloth_mesh(mesh, material=material, vel=vel)

    def add_cloth_usd(self, path, *, material: Material, prim_path: str | None = None,
                      vel: Sequence[float] | None = None) -> int:
        """Add a cloth from a USD mesh prim (material coordinates from its ``st``/``uv`` primvar if present)."""
        return self.add_cloth_mesh(mesh_io.load_usd_mesh(path, prim_path=prim_path), material=material, vel=vel)

    # -- handles -----------------------------------------------------------------------------------------------------
    def _check_size(self, added: int, what: str) -> None:
        total = self._particle_count + added
        if total > self.max_particles:
            raise ValueError(
                f"{what} makes {total:,} particles, more than ModelBuilder.max_particles = {self.max_particles:,} "
                f"(about {self.BYTES_PER_PARTICLE * total / 2**30:.0f} GiB to simulate); use a coarser cloth, or "
                "raise max_particles on a machine with that memory")

    def _check_particle(self, what: str, particle: int) -> int:
        if not _is_integer(particle):
            raise TypeError(f"{what}: particle must be an integer index, got {type(particle).__name__} {particle!r}")
        p = int(particle)
        if not 0 <= p < self._particle_count:
            raise ValueError(f"{what}: particle {particle} out of range [0, {self._particle_count})")
        return p

    def add_handle(self, particle: int, *, stiffness: float = DEFAULT_HANDLE_STIFFNESS, motion=None,
                   window: tuple[float, float] | None = None) -> int:
        """Hold ``particle`` by a spring ``1/2 k |x - target|^2`` (``k`` [N/m]) to its initial position plus
        ``Control.handle_target``'s change and ``motion`` (``(time [s], (dx, dy, dz) [m])`` keys, or an object with
        ``at(t) -> offset``); ``window`` (on, off) [s]: it holds in the steps that end in (on, off] only. Returns its
        index."""
        self._check_own("add_handle")
        p = self._check_particle("add_handle", particle)
        if any(h[0] == p for h in self._handles):
            raise ValueError(f"particle {p} has a handle already")
        k = float(stiffness)
        if not math.isfinite(k) or k < 0.0:
            raise ValueError(f"handle on particle {p}: stiffness must be finite and >= 0, got {stiffness}")
        if window is not None:
            on, off = (float(w) for w in window)
            if math.isnan(on) or math.isnan(off) or not off > on:
                raise ValueError(f"handle on particle {p}: window (on, off) must have off > on, got {window}")
            window = (on, off)
        if motion is not None and callable(getattr(motion, "at", None)) and not isinstance(motion, Motion):
            self._handles.append((p, k, motion, window))
        else:
            self._handles.append((p, k, _motion(f"handle on particle {p}", motion), window))
        return len(self._handles) - 1

    def add_gripper(self, gripper) -> list[int]:
        """Hold a :class:`warpcloth.grippers.Gripper`'s particles by handles of its stiffness, on between its grasp
        and release, their scripted motion its knots'; returns the handles' indices.

        Raises:
            ValueError: a particle the cloth lacks, or one another gripper or handle holds already (naming them)."""
        from warpcloth.grippers import Gripper, GripperMotion

        self._check_own("add_gripper")
        if not isinstance(gripper, Gripper):
            raise TypeError(f"add_gripper: expected a warpcloth.grippers.Gripper, got {type(gripper).__name__}")
        held = {p: g.name for g in self._grippers for p in g.particles}
        for p in gripper.particles:
            if not _is_integer(p) or not 0 <= p < self._particle_count:
                raise ValueError(f"{gripper.name}: particle {p} out of range: the cloth has {self._particle_count} "
                                 "particles")
            if p in held:
                raise ValueError(f"{gripper.name}: particle {p} is held by {held[p]} already")
            if any(h[0] == p for h in self._handles):
                raise ValueError(f"{gripper.name}: particle {p} has a handle already")
        x0 = np.concatenate(self._positions)[list(gripper.particles)]
        handles = [self.add_handle(p, stiffness=gripper.stiffness, motion=GripperMotion(gripper, x0, j),
                                   window=(gripper.grasp, gripper.release)) for j, p in enumerate(gripper.particles)]
        self._grippers.append(gripper)
        return handles

    def add_pin(self, particle: int, *, motion=None) -> int:
        """Fix ``particle`` exactly to a target (its velocity is prescribed); ``motion`` as in :meth:`add_handle`."""
        self._check_own("add_pin")
        p = self._check_particle("add_pin", particle)
        if any(q == p for q, _ in self._pins):
            raise ValueError(f"particle {p} is pinned twice")
        self._pins.append((p, _motion(f"pin on particle {p}", motion)))
        return len(self._pins) - 1

    # -- obstacles ---------------------------------------------------------------------------------------------------
    def add_obstacle_mesh(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        *,
        name: str | None = None,
        pos: Sequence[float] = (0.0, 0.0, 0.0),
        rot=None,
        motion=None,
    ) -> int:
        """Add a rigid obstacle of body-frame ``vertices`` [m] (V, 3) and ``triangles`` (T, 3), counter-clockwise seen
        from the cloth, not necessarily closed; returns its index. It turns on cloth-obstacle collisions.

        A vertex ``u`` is at ``M(t) (R u + pos)``: the base placement (``rot``, a 3x3 matrix or unit quaternion
        (x, y, z, w), ``pos`` [m]; differentiable as ``Control.obstacle_transform``), then ``motion`` ``M(t)``, a
        ``RigidMotion`` or keyframes ``[(time [s], (tx, ty, tz) [m], (qx, qy, qz, qw)), ...]``. ``name``: a USD
        identifier unique among the obstacles, default ``"obstacle<k>"``.

        Raises:
            ValueError: naming the obstacle: a repeated or invalid name, bad placement or motion, a non-finite
                vertex, an index out of range or a degenerate triangle."""
        self._check_own("add_obstacle_mesh")
        index = len(self._obstacles)
        taken = {o.name for o in self._obstacles}
        if name is None:
            k = index
            while f"obstacle{k}" in taken:
                k += 1
            name = f"obstacle{k}"
        elif name in taken:
            raise ValueError(f"obstacle name {name!r} is used twice; obstacle names must be unique")
        what = f"obstacle {name!r}"
        transform = placement(what, pos, rot)
        if motion is not None and not isinstance(motion, RigidMotion):
            try:
                motion = RigidMotion.from_keyframes(motion)
            except (ValueError, TypeError) as exc:
                raise ValueError(f"{what}: {exc}") from None
        self._obstacles.append(Obstacle(name, vertices, triangles, transform, motion))
        return index

    def add_obstacle_obj(self, path, *, scale: float = 1.0, name: str | None = None,
                         pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None, motion=None) -> int:
        """Add an obstacle from an OBJ file scaled by ``scale`` (the body frame); see :meth:`add_obstacle_mesh`."""
        mesh = mesh_io.load_obj(path, scale=scale, validate=False)
        try:
            return self.add_obstacle_mesh(mesh.positions, mesh.triangles, name=name, pos=pos, rot=rot, motion=motion)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

    def add_obstacle_usd(self, path, *, prim_path: str | None = None, scale: float = 1.0, name: str | None = None,
                         pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None, motion=None) -> int:
        """Add an obstacle from a USD mesh prim scaled by ``scale`` (the body frame); see :meth:`add_obstacle_mesh`."""
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
            raise ValueError(f"add_obstacle_usd: scale must be a finite number > 0, got {scale!r}")
        mesh = mesh_io.load_usd_mesh(path, prim_path=prim_path, validate=False)
        try:
            return self.add_obstacle_mesh(mesh.positions * scale, mesh.triangles, name=name, pos=pos, rot=rot,
                                          motion=motion)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

    def add_obstacle_plane(self, size: Sequence[float] = (1.0, 1.0), res: Sequence[int] = (1, 1), *,
                           name: str | None = None, pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None,
                           motion=None) -> int:
        """Add a rectangle (:func:`~warpcloth.plane_mesh`: centred, body XY plane, facing +z)."""
        vertices, triangles = plane_mesh(size, res)
        return self.add_obstacle_mesh(vertices, triangles, name=name, pos=pos, rot=rot, motion=motion)

    def add_obstacle_box(self, half_extents: Sequence[float], *, name: str | None = None,
                         pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None, motion=None) -> int:
        """Add a box of half sizes ``half_extents`` [m] centred on its body origin (:func:`~warpcloth.box_mesh`)."""
        vertices, triangles = box_mesh(half_extents)
        return self.add_obstacle_mesh(vertices, triangles, name=name, pos=pos, rot=rot, motion=motion)

    def add_obstacle_sphere(self, radius: float, subdivisions: int = 3, *, name: str | None = None,
                            pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None, motion=None) -> int:
        """Add an icosphere of ``radius`` [m] centred on its body origin (:func:`~warpcloth.sphere_mesh`)."""
        vertices, triangles = sphere_mesh(radius, subdivisions)
        return self.add_obstacle_mesh(vertices, triangles, name=name, pos=pos, rot=rot, motion=motion)

    def add_obstacle_funnel(self, *, name: str | None = None, pos: Sequence[float] = (0.0, 0.0, 0.0), rot=None,
                            motion=None) -> int:
        """Add the seed's funnel (:func:`~warpcloth.funnel_mesh`; the seed places it at ``(-0.5, -1, -0.55)``)."""
        vertices, triangles = funnel_mesh()
        return self.add_obstacle_mesh(vertices, triangles, name=name, pos=pos, rot=rot, motion=motion)

    def set_collision(self, *, self_collision: bool = False, thickness: float = DEFAULT_COLLISION_THICKNESS,
                      repulsion_thickness: float = DEFAULT_REPULSION_THICKNESS,
                      repulsion_stiffness: float = DEFAULT_REPULSION_STIFFNESS, friction: float = DEFAULT_FRICTION,
                      obstacle_friction: float = DEFAULT_OBSTACLE_FRICTION) -> None:
        """Collision settings, defaults ARCSim's; see :class:`~warpcloth.CollisionSettings`. ``repulsion_stiffness``
        [N/m^3] >= 0 acts per m^2 of rest area; ``friction``, ``obstacle_friction`` >= 0: Coulomb coefficients,
        cloth-cloth and cloth-obstacle; 0 turns a force off. ValueError for a setting out of range."""
        self._check_own("set_collision")
        if not isinstance(self_collision, (bool, np.bool_)):
            raise ValueError(f"self_collision must be a boolean, got {self_collision!r}")
        for name, value, positive in (("collision thickness", thickness, True),
                                      ("repulsion_thickness", repulsion_thickness, True),
                                      ("repulsion_stiffness", repulsion_stiffness, False),
                                      ("friction", friction, False), ("obstacle_friction", obstacle_friction, False)):
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
                raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'}, got {value}")
        self.self_collision = bool(self_collision)
        self.collision_thickness = float(thickness)
        self.repulsion = (float(repulsion_thickness), float(repulsion_stiffness), float(friction),
                          float(obstacle_friction))

    # -- scene forces --------------------------------------------------------------------------------------------
    def set_wind(self, velocity: Sequence[float], *, density: float = 1.0, drag: float = 0.0,
                 lagged_normals: bool = False) -> None:
        """Constant wind ``velocity`` [m/s] (ARCSim ``wind_force``): pressure ``density*A*|vn|*vn`` (``density``
        [kg/m^3]), drag ``drag*A*vt`` (``drag`` [kg/(m^2 s)]). ``lagged_normals``: face normals from the last step's
        start positions (the current ones after a collision response), as ARCSim does."""
        self._check_own("set_wind")
        v = _finite_vector("wind velocity", velocity)
        for name, val in (("wind density", density), ("wind drag", drag)):
            if not math.isfinite(val) or val < 0.0:
                raise ValueError(f"{name} must be finite and >= 0, got {val}")
        self.wind = (v, float(density), float(drag))
        self.wind_lagged_normals = bool(lagged_normals)

    def set_damping(self, *, mass: float = 0.0, stiffness: float = 0.0) -> None:
        """Rayleigh damping: ``mass`` alpha [1/s] (force -alpha M v), ``stiffness`` beta [s] (force -beta K v)."""
        self._check_own("set_damping")
        for name, val in (("damping mass", mass), ("damping stiffness", stiffness)):
            if not math.isfinite(val) or val < 0.0:
                raise ValueError(f"{name} must be finite and >= 0, got {val}")
        self.damping_mass = float(mass)
        self.damping_stiffness = float(stiffness)

    # -- finalize ---------------------------------------------------------------------------------------------------
    def finalize(self, device=None, *, requires_grad: bool = False, dtype=wp.float32) -> Model:
        """Build the Model on Warp ``device`` (default: Warp's) with floats of ``dtype`` (``wp.float32`` or
        ``wp.float64``); ``requires_grad`` gives gradients to materials, gravity, wind, states, handle stiffness,
        contact parameters and obstacle vertices. ValueError: no cloth, another dtype, or a pinned handle."""
        if not self._triangles:
            raise ValueError("the model has no cloth: add one with add_cloth_grid/add_cloth_mesh first")
        if dtype not in (wp.float32, wp.float64):
            raise ValueError(f"dtype must be wp.float32 or wp.float64, got {dtype}")
        device = wp.get_device(device)
        from warpcloth.kernels.types import types

        t = types(dtype)
        worlds = self._worlds or [self._own_world()]
        damping_mass, damping_stiffness, self_collision, collision_thickness, repulsion, lagged = worlds[0].shared
        positions = np.concatenate(self._positions)
        velocities = np.concatenate(self._velocities)
        triangles = np.concatenate(self._triangles).astype(np.int32)
        tri_uv = np.concatenate(self._tri_uv)
        tri_material = np.concatenate(self._tri_material)
        n = len(positions)

        dm = np.stack([tri_uv[:, 1] - tri_uv[:, 0], tri_uv[:, 2] - tri_uv[:, 0]], axis=-1)  # (T, 2, 2) columns
        det = np.linalg.det(dm)
        area = 0.5 * det
        inv_dm = np.linalg.inv(dm)
        particle_area = np.zeros(n)
        for c in range(3):
            np.add.at(particle_area, triangles[:, c], area / 3.0)

        hinges, h_face0, h_uv0, h_uv1, h_area, h_mat = _hinges(triangles, tri_uv, area, tri_material)
        rest_length = np.linalg.norm(h_uv0[:, 1] - h_uv0[:, 0], axis=1) if len(hinges) else np.zeros(0)
        direction = (
            np.stack([fold_direction(h_uv0[:, 1] - h_uv0[:, 0]), fold_direction(h_uv1[:, 1] - h_uv1[:, 0])], -1)
            if len(hinges)
            else np.zeros((0, 2))
        )
        rest_angle = np.zeros(len(hinges))
        initial = np.concatenate([np.full(len(tr), f) for tr, f in zip(self._triangles, self._rest_angle_initial)])
        if len(hinges) and initial.any():
            theta = _dihedral_angles(positions, hinges)
            face0_initial = initial[h_face0]
            rest_angle = np.where(face0_initial, theta, 0.0)

        offsets, columns, tri_slot, hinge_slot, diag_slot = _block_structure(n, triangles, hinges)

        pin_of = np.full(n, -1, dtype=np.int32)
        for q, (p, _) in enumerate(self._pins):
            pin_of[p] = q
        for p, *_ in self._handles:
            if pin_of[p] >= 0:
                raise ValueError(f"particle {p} has both a hard pin and a soft handle; keep one")

        def arr(values, dtype_, rg=False):
            return wp.array(values, dtype=dtype_, device=device, requires_grad=rg and requires_grad)

        scalar = t.scalar
        lut_w, lut_r = stretching_lut()
        mats = self._materials
        edges = unique_edges(triangles)
        obstacle_fields = self._obstacle_fields(arr, t)
        collision = None
        if self._obstacles or self_collision:
            collision = CollisionSettings(
                obstacles=bool(self._obstacles), self_collision=self_collision,
                thickness=collision_thickness, repulsion_thickness=repulsion[0],
            )
        world_start = np.array([w.first_particle for w in worlds] + [n], dtype=np.int64)
        obstacle_start = [w.first_obstacle for w in worlds] + [len(self._obstacles)]
        windy = [w for w in worlds if w.wind is not None]
        wind = None
        if windy:  # a world without wind has none: no pressure (density 0) and no drag
            wind = (np.stack([w.wind[0] if w.wind else np.zeros(3) for w in worlds]),
                    np.array([w.wind[1] if w.wind else 0.0 for w in worlds]),
                    np.array([w.wind[2] if w.wind else 0.0 for w in worlds]))
        model = Model(
            device=device,
            scalar=scalar,
            requires_grad=requires_grad,
            particle_count=n,
            particle_x0=arr(positions, t.vec3, True),
            particle_v0=arr(velocities, t.vec3, True),
            particle_pin=arr(pin_of, wp.int32),
            particle_diag_slot=arr(diag_slot, wp.int32),
            tri_count=len(triangles),
            tri_indices=arr(triangles, wp.int32),
            tri_material=arr(tri_material, wp.int32),
            tri_inv_dm=arr(inv_dm, t.mat22),
            tri_area=arr(area, scalar),
            tri_block_slot=arr(tri_slot, wp.int32),
            hinge_count=len(hinges),
            hinge_indices=arr(hinges.reshape(-1, 4), wp.int32),
            hinge_material=arr(h_mat, wp.int32),
            hinge_rest_angle=arr(rest_angle, scalar),
            hinge_rest_length=arr(rest_length, scalar),
            hinge_rest_area=arr(h_area, scalar),
            hinge_direction=arr(direction.reshape(-1, 2), t.vec2),
            hinge_block_slot=arr(hinge_slot.reshape(-1, 16), wp.int32),
            material_count=len(mats),
            material_names=[m.name for m in mats],
            material_density=arr(np.array([m.density for m in mats]), scalar, True),
            material_stretching=arr(np.array([m.stretching for m in mats]), scalar, True),
            material_bending=arr(np.array([m.bending for m in mats]), scalar, True),
            material_thicken=arr(np.array([m.thicken for m in mats]), scalar),
            lut_weight=arr(lut_w, t.vec3),
            lut_row=arr(lut_r, wp.int32),
            world_count=len(worlds),
            particle_world=arr(np.repeat(np.arange(len(worlds), dtype=np.int32), np.diff(world_start)), wp.int32),
            world_particle_start=world_start,
            gravity=arr(np.stack([w.gravity for w in worlds]), t.vec3, True),
            wind_velocity=None if wind is None else arr(wind[0], t.vec3, True),
            wind_density=None if wind is None else arr(wind[1], scalar, True),
            wind_drag=None if wind is None else arr(wind[2], scalar, True),
            wind_lagged_normals=lagged,
            damping_mass=arr(np.array([damping_mass]), scalar, True),
            damping_stiffness=arr(np.array([damping_stiffness]), scalar, True),
            handle_count=len(self._handles),
            handle_particle=arr(np.array([h[0] for h in self._handles], dtype=np.int32), wp.int32),
            handle_stiffness=arr(np.array([h[1] for h in self._handles]), scalar, True),
            handle_rest_target=positions[[h[0] for h in self._handles]].reshape(-1, 3),
            handle_motion=[h[2] for h in self._handles],
            handle_window=(None if all(h[3] is None for h in self._handles) else
                           np.array([h[3] or (-math.inf, math.inf) for h in self._handles], dtype=np.float64)),
            grippers=list(self._grippers),
            pin_count=len(self._pins),
            pin_particle=arr(np.array([p[0] for p in self._pins], dtype=np.int32), wp.int32),
            pin_rest_target=positions[[p[0] for p in self._pins]].reshape(-1, 3),
            pin_motion=[p[1] for p in self._pins],
            bsr_offsets=arr(offsets, wp.int32),
            bsr_columns=arr(columns, wp.int32),
            triangles_np=triangles,
            edge_count=len(edges),
            edge_indices=arr(edges, wp.int32),
            collision=collision,
            contact_repulsion_stiffness=None if collision is None else arr(np.array([repulsion[1]]), scalar, True),
            contact_friction=None if collision is None else arr(np.array(repulsion[2:]), scalar, True),
            obstacle_world=np.repeat(np.arange(len(worlds), dtype=np.int32), np.diff(obstacle_start)),
            particle_area=arr(particle_area, scalar),
            **obstacle_fields,
        )
        return model

    def _obstacle_fields(self, arr, t) -> dict:
        obs = self._obstacles
        if not obs:
            return {}
        v_start = np.cumsum([0] + [o.vertex_count for o in obs]).astype(np.int64)
        t_start = np.cumsum([0] + [o.triangle_count for o in obs]).astype(np.int64)
        local = np.concatenate([o.vertices for o in obs])
        body = np.repeat(np.arange(len(obs), dtype=np.int32), [o.vertex_count for o in obs])
        tris = np.concatenate([o.triangles.astype(np.int64) + v_start[b] for b, o in enumerate(obs)])
        if v_start[-1] > np.iinfo(np.int32).max:
            raise ValueError(f"the obstacles have {v_start[-1]} vertices in all; at most 2**31 - 1 fit int32 indices")
        tris = tris.astype(np.int32)
        edges = contact_edges(local, tris)  # in the body frames: rigid motion keeps flat edges flat
        return dict(
            obstacle_count=len(obs),
            obstacle_names=[o.name for o in obs],
            obstacle_vertex_count=len(local),
            obstacle_vertex_local=arr(local, t.vec3, True),
            obstacle_vertex_body=arr(body, wp.int32),
            obstacle_vertex_start=v_start,
            obstacle_tri_count=len(tris),
            obstacle_tri_indices=arr(tris, wp.int32),
            obstacle_tri_start=t_start,
            obstacle_edge_count=len(edges),
            obstacle_edge_indices=arr(edges, wp.int32),
            obstacle_rest_transform=np.stack([o.transform for o in obs]),
            obstacle_motion=[o.motion for o in obs],
            obstacle_triangles_np=tris,
        )


def _hinges(triangles, tri_uv, area, tri_material):
    """Interior edges as (x0, x1, x2, x3) hinges, face 0, the edge's material coordinates in both faces."""
    T = len(triangles)
    a = triangles.reshape(-1)
    b = triangles[:, [1, 2, 0]].reshape(-1)
    c = triangles[:, [2, 0, 1]].reshape(-1)
    face = np.repeat(np.arange(T), 3)
    corner = np.tile(np.arange(3), T)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo.astype(np.int64) * (int(a.max()) + 1) + hi
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    counts = np.diff(np.r_[starts, len(key_sorted)])
    if np.any(counts > 2):
        g = int(np.flatnonzero(counts > 2)[0])
        members = order[starts[g]: starts[g] + counts[g]]
        raise ValueError(
            f"non-manifold edge ({a[members[0]]}, {b[members[0]]}) is shared by triangles "
            f"{sorted(int(face[m]) for m in members)}; an edge may border at most two triangles"
        )
    pairs = starts[counts == 2]
    e0 = order[pairs]
    e1 = order[pairs + 1]
    same_direction = a[e0] == a[e1]
    if np.any(same_direction):
        g = int(np.flatnonzero(same_direction)[0])
        raise ValueError(
            f"triangles {int(face[e0[g]])} and {int(face[e1[g]])} traverse their shared edge "
            f"({a[e0[g]]}, {b[e0[g]]}) in the same direction: the mesh winding is inconsistent"
        )
    hinges = np.stack([a[e0], b[e0], c[e0], c[e1]], axis=1).astype(np.int32)
    f0, f1 = face[e0], face[e1]
    k0, k1 = corner[e0], corner[e1]
    uv0 = np.stack([tri_uv[f0, k0], tri_uv[f0, (k0 + 1) % 3]], axis=1)
    uv1 = np.stack([tri_uv[f1, (k1 + 1) % 3], tri_uv[f1, k1]], axis=1)  # face 1 runs b -> a
    return hinges, f0, uv0, uv1, area[f0] + area[f1], tri_material[f0].astype(np.int32)


def _dihedral_angles(positions: np.ndarray, hinges: np.ndarray) -> np.ndarray:
    x0, x1, x2, x3 = (positions[hinges[:, c]] for c in range(4))
    n0 = np.cross(x1 - x0, x2 - x0)
    n1 = np.cross(x3 - x0, x1 - x0)
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    e = x0 - x1
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    return np.arctan2(np.einsum("ij,ij->i", e, np.cross(n0, n1)), np.einsum("ij,ij->i", n0, n1))


def _block_structure(n, triangles, hinges):
    """Block-sparse pattern of A (vertex pairs sharing a triangle or hinge): CSR offsets, columns, element slots."""
    tri_rows = np.repeat(triangles, 3, axis=1).reshape(-1)
    tri_cols = np.tile(triangles, (1, 3)).reshape(-1)
    h_rows = np.repeat(hinges, 4, axis=1).reshape(-1)
    h_cols = np.tile(hinges, (1, 4)).reshape(-1)
    diag = np.arange(n)
    rows = np.concatenate([tri_rows, h_rows, diag]).astype(np.int64)
    cols = np.concatenate([tri_cols, h_cols, diag]).astype(np.int64)
    keys = np.unique(rows * n + cols)
    columns = (keys % n).astype(np.int32)
    offsets = np.zeros(n + 1, dtype=np.int32)
    np.add.at(offsets, (keys // n) + 1, 1)
    offsets = np.cumsum(offsets).astype(np.int32)

    def slot(r, c):
        return np.searchsorted(keys, r.astype(np.int64) * n + c).astype(np.int32)

    tri_slot = slot(tri_rows, tri_cols).reshape(-1, 9)
    hinge_slot = slot(h_rows, h_cols).reshape(-1, 16)
    return offsets, columns, tri_slot, hinge_slot, slot(diag, diag)


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))

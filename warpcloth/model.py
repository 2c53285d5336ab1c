"""Model (static), State (per step) and Control (what users optimise), after Newton's data model."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warpcloth.geometry.motion import RigidMotion
from warpcloth.kernels.types import types


class State:
    """Particles at one instant and what their step hands to the next; positions and velocities alone start one."""

    def __init__(self, particle_x: wp.array, particle_v: wp.array, time: float = 0.0, *, step: int = 0,
                 particle_dv: wp.array | None = None, particle_x_previous: wp.array | None = None,
                 particle_x_last: wp.array | None = None, particle_v_last: wp.array | None = None):
        self.particle_x = particle_x
        """Particle positions [m], shape (particle_count,), vec3."""
        self.particle_v = particle_v
        """Particle velocities [m/s], shape (particle_count,), vec3."""
        self.time = time
        """Simulated time [s], scalar (host)."""
        self.step = step
        """Steps taken since the start of the trajectory [-], scalar (host int)."""
        self.particle_dv = particle_dv
        """Last solve's velocity change [m/s], (particle_count,) vec3: next solve's first guess; None: zero."""
        self.particle_x_previous = particle_x_previous
        """Positions [m] at the last step's start, (particle_count,) vec3, for lagged wind normals; None: current."""
        self.particle_x_last = particle_x_last
        """Positions [m] one step before, (particle_count,) vec3, for ``integrator="bdf2"``; None otherwise."""
        self.particle_v_last = particle_v_last
        """Velocities [m/s] one step before, (particle_count,) vec3 (as ``particle_x_last``)."""
        self.solve_adjoint = None
        """Adjoint solve of the step that read this state [m/s per unit loss], (particle_count,) vec3, or None."""

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities as NumPy arrays (particle_count, 3)."""
        return self.particle_x.numpy(), self.particle_v.numpy()

    def clone(self, *, requires_grad: bool | None = None) -> State:
        """A deep copy (``requires_grad`` None: ``particle_x``'s); stepping it repeats the original's next step."""
        rg = self.particle_x.requires_grad if requires_grad is None else requires_grad

        def copy(a):
            return None if a is None else wp.clone(a, requires_grad=rg)

        x = copy(self.particle_x)
        # after a collision response the lagged normals' positions are the current ones (the same array)
        previous = x if self.particle_x_previous is self.particle_x else copy(self.particle_x_previous)
        # with lagged normals and no collision response, the normals' positions are the last step's
        x_last = copy(self.particle_x_last)
        if self.particle_x_previous is not None and self.particle_x_previous is self.particle_x_last:
            previous = x_last
        return State(x, copy(self.particle_v), self.time, step=self.step,
                     particle_dv=None if self.particle_dv is None else wp.clone(self.particle_dv, requires_grad=False),
                     particle_x_previous=previous, particle_x_last=x_last,
                     particle_v_last=copy(self.particle_v_last))


class Control:
    """Inputs applied during a step; every array here can carry gradients."""

    def __init__(
        self,
        particle_force: wp.array | None,
        handle_target: wp.array,
        pin_target: wp.array,
        *,
        obstacle_transform: wp.array | None = None,
    ):
        self.particle_force = particle_force
        """External force per particle [N], shape (particle_count,), or None (then nothing is launched for it)."""
        self.handle_target = handle_target
        """Base target of each soft handle [m], shape (handle_count,); scripted motion adds to it."""
        self.pin_target = pin_target
        """Base target of each hard pin [m], shape (pin_count,); scripted motion adds to it."""
        self.obstacle_transform = obstacle_transform
        """Base placement of each obstacle ([m], quaternion (x, y, z, w)), (obstacle_count,) transform, or None."""


@dataclass(frozen=True)
class CollisionSettings:
    """Which collisions a model has (``obstacles`` whenever it has an obstacle) and how thick they are."""

    obstacles: bool
    self_collision: bool
    thickness: float
    """Collision thickness delta [m], > 0: the distance the response keeps between the cloth and what it touches."""
    repulsion_thickness: float = 5.0e-3
    """Proximity repulsion thickness [m], > 0: pairs within twice it are found, the penalty acts within it."""

    def __post_init__(self):
        for name in ("thickness", "repulsion_thickness"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(f"collision {name} must be finite and > 0 [m], got {value}")


@dataclass
class Motion:
    """Piecewise-linear target displacement, ``offsets`` [m] (K, 3) at increasing ``times`` [s] (K,), flat outside."""

    times: np.ndarray
    offsets: np.ndarray

    def at(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.times, self.offsets[:, d]) for d in range(3)])


@dataclass
class Model:
    """What does not change while a scene runs, from ``ModelBuilder.finalize``; (host) fields are Python or NumPy."""

    device: wp.context.Device
    """Warp device every array lives on [-], scalar (host)."""
    scalar: type
    """Scalar type of every float array (wp.float32 or wp.float64) [-], scalar (host)."""
    requires_grad: bool
    """Whether the differentiable arrays carry gradients [-], scalar (host)."""

    particle_count: int
    """Number of cloth particles [-], scalar (host)."""
    particle_x0: wp.array
    """Initial particle positions [m], (particle_count,) vec3."""
    particle_v0: wp.array
    """Initial particle velocities [m/s], (particle_count,) vec3."""
    particle_pin: wp.array
    """Index of the hard pin holding each particle, or -1 [-], (particle_count,) int32."""
    particle_diag_slot: wp.array
    """BSR block slot of each particle's diagonal block [-], (particle_count,) int32."""

    tri_count: int
    """Number of cloth triangles [-], scalar (host)."""
    tri_indices: wp.array
    """Triangle vertex indices [-], (tri_count, 3) int32."""
    tri_material: wp.array
    """Material index of each triangle [-], (tri_count,) int32."""
    tri_inv_dm: wp.array
    """Inverse material-space edge matrix Dm^-1 [1/m], (tri_count,) mat22."""
    tri_area: wp.array
    """Material-space (rest) area [m^2], (tri_count,)."""
    tri_block_slot: wp.array
    """BSR slots of the 9 vertex-pair blocks of each triangle (row-major a*3+b) [-], (tri_count, 9) int32."""

    hinge_count: int
    """Number of interior edges (bending hinges) [-], scalar (host)."""
    hinge_indices: wp.array
    """Interior edges (x0, x1, x2, x3): edge x0-x1, x2 and x3 opposite [-], (hinge_count, 4) int32."""
    hinge_material: wp.array
    """Material of each hinge (that of face 0) [-], (hinge_count,) int32."""
    hinge_rest_angle: wp.array
    """Rest dihedral angle [rad], (hinge_count,)."""
    hinge_rest_length: wp.array
    """Material-space edge length [m], (hinge_count,)."""
    hinge_rest_area: wp.array
    """Sum of the two faces' rest areas A0 + A1 [m^2], (hinge_count,)."""
    hinge_direction: wp.array
    """Bending-table direction index of the edge in each face's material frame, in [0, 2], (hinge_count,) vec2."""
    hinge_block_slot: wp.array
    """BSR slots of the 16 vertex-pair blocks of each hinge [-], (hinge_count, 16) int32."""

    material_count: int
    """Number of materials [-], scalar (host)."""
    material_names: list[str]
    """Name of each material [-], (material_count,) (host)."""
    material_density: wp.array
    """Area density [kg/m^2] before thicken, (material_count,)."""
    material_stretching: wp.array
    """Stretching table [N/m] before thicken, (material_count, 6, 4)."""
    material_bending: wp.array
    """Bending table [N*m] before thicken, (material_count, 3, 5)."""
    material_thicken: wp.array
    """ARCSim thicken factor on density, stretching and bending [-], (material_count,)."""
    lut_weight: wp.array
    """Stretching lookup: weights of table rows (0, r+1, r+2) per cell [-], (27000,) vec3."""
    lut_row: wp.array
    """Stretching lookup: angle row r per cell [-], (27000,) int32."""

    world_count: int
    """Number of independent worlds (``ModelBuilder.add_world``) [-], scalar (host)."""
    particle_world: wp.array
    """World of each particle [-], (particle_count,) int32."""
    world_particle_start: np.ndarray
    """First particle of each world, then particle_count [-], (world_count + 1,) int64 (host)."""
    gravity: wp.array
    """Gravitational acceleration of each world [m/s^2], (world_count,) vec3."""
    wind_velocity: wp.array | None
    """Wind velocity of each world [m/s], (world_count,) vec3; None when no world has wind."""
    wind_density: wp.array | None
    """Air density of each world's wind pressure [kg/m^3], (world_count,) (0 in a world without wind)."""
    wind_drag: wp.array | None
    """Tangential drag coefficient of each world's wind [kg/(m^2 s)], (world_count,) (0 in a world without wind)."""
    wind_lagged_normals: bool
    """Wind uses the last step's start normals (ARCSim's lag) [-], scalar (host)."""
    damping_mass: wp.array
    """Rayleigh mass-proportional damping alpha [1/s] of every world, (1,); takes gradients."""
    damping_stiffness: wp.array
    """Rayleigh stiffness-proportional damping beta [s] (ARCSim's material ``damping``) of every world, (1,); takes
    gradients."""

    handle_count: int
    """Number of soft handles [-], scalar (host)."""
    handle_particle: wp.array | None
    """Particle held by each soft handle [-], (handle_count,) int32."""
    handle_stiffness: wp.array | None
    """Soft handle stiffness [N/m], (handle_count,)."""
    handle_rest_target: np.ndarray
    """Default handle targets (the particles' initial positions) [m], (handle_count, 3)."""
    handle_motion: list[Motion | None]
    """Scripted motion of each handle target (offsets [m] over time [s]) or None, (handle_count,) (host)."""
    pin_count: int
    """Number of hard pins [-], scalar (host)."""
    pin_particle: wp.array | None
    """Particle held by each hard pin [-], (pin_count,) int32."""
    pin_rest_target: np.ndarray
    """Default pin targets [m], (pin_count, 3)."""
    pin_motion: list[Motion | None]
    """Scripted motion of each pin target (offsets [m] over time [s]) or None, (pin_count,) (host)."""

    bsr_offsets: wp.array
    """Row offsets of the fixed block-sparse structure [-], (particle_count + 1,) int32."""
    bsr_columns: wp.array
    """Block column of each stored block [-], (nnz,) int32."""
    triangles_np: np.ndarray = field(repr=False, default=None)
    """Host copy of tri_indices, for I/O [-], (tri_count, 3) int32."""

    edge_count: int = 0
    """Number of unique cloth edges [-], scalar (host)."""
    edge_indices: wp.array | None = None
    """Unique undirected cloth edges (lo, hi) with lo < hi, rows sorted, each edge once [-], (edge_count, 2) int32."""

    particle_area: wp.array | None = None
    """Rest area of each particle (a third of its triangles') [m^2], (particle_count,)."""

    collision: CollisionSettings | None = None
    """Collision settings [-], scalar (host); None without obstacles and self-collision."""
    contact_repulsion_stiffness: wp.array | None = None
    """Repulsion stiffness per m^2 of rest area [N/m^3], (1,); 0: off. Takes gradients; None without collisions."""
    contact_friction: wp.array | None = None
    """Coulomb friction coefficients [-], (2,): cloth-cloth, cloth-obstacle. Takes gradients; None if no collisions."""

    # Obstacles. All obstacles' meshes are concatenated; with no obstacle every array below is None.
    obstacle_count: int = 0
    """Number of rigid obstacles [-], scalar (host)."""
    obstacle_names: list[str] = field(default_factory=list)
    """Name of each obstacle (a valid USD identifier) [-], (obstacle_count,)."""
    obstacle_vertex_count: int = 0
    """Number of obstacle vertices, all obstacles together [-], scalar (host)."""
    obstacle_vertex_local: wp.array | None = None
    """Obstacle vertices in their body frames [m], (obstacle_vertex_count,) vec3. Takes gradients."""
    obstacle_vertex_body: wp.array | None = None
    """Obstacle index of each obstacle vertex [-], (obstacle_vertex_count,) int32."""
    obstacle_vertex_start: np.ndarray | None = field(repr=False, default=None)
    """First vertex of each obstacle in the concatenated list, and the total [-], (obstacle_count + 1,) int64 (host)."""
    obstacle_tri_count: int = 0
    """Number of obstacle triangles, all obstacles together [-], scalar (host)."""
    obstacle_tri_indices: wp.array | None = None
    """Obstacle triangles, indices into the concatenated vertex list [-], (obstacle_tri_count, 3) int32."""
    obstacle_tri_start: np.ndarray | None = field(repr=False, default=None)
    """First triangle of each obstacle, and the total [-], (obstacle_count + 1,) int64 (host)."""
    obstacle_edge_count: int = 0
    """Number of obstacle contact edges, all obstacles together [-], scalar (host)."""
    obstacle_edge_indices: wp.array | None = None
    """Obstacle contact edges (lo, hi), lo < hi, all but flat ones (``contact_edges``) [-], (obstacle_edge_count, 2)."""
    obstacle_rest_transform: np.ndarray | None = None
    """Base placement (px, py, pz [m], qx, qy, qz, qw), (obstacle_count, 7) float64 (host): ``control()``'s."""
    obstacle_motion: list[RigidMotion | None] = field(default_factory=list)
    """Scripted motion of each obstacle, or None for a static one [-], (obstacle_count,)."""
    obstacle_triangles_np: np.ndarray | None = field(repr=False, default=None)
    """Host copy of obstacle_tri_indices, for I/O [-], (obstacle_tri_count, 3) int32."""
    obstacle_world: np.ndarray | None = field(repr=False, default=None)
    """World of each obstacle [-], (obstacle_count,) int32 (host)."""
    handle_window: np.ndarray | None = None
    """When each handle holds [s], (handle_count, 2) (host): in the steps that end in (on, off]; None: always."""
    grippers: list = field(default_factory=list)
    """The grippers (:class:`warpcloth.grippers.Gripper`) whose handles the model holds [-], (gripper_count,) (host)."""

    @property
    def types(self):
        return types(self.scalar)

    def world_slice(self, world: int) -> slice:
        """The particle range of ``world``: ``state.particle_x[model.world_slice(w)]`` is a view of its positions."""
        if not isinstance(world, (int, np.integer)) or isinstance(world, bool) or not 0 <= world < self.world_count:
            raise ValueError(f"world {world!r} out of range [0, {self.world_count})")
        return slice(int(self.world_particle_start[world]), int(self.world_particle_start[world + 1]))

    def world_of(self, particle: int) -> int:
        return int(np.searchsorted(self.world_particle_start, particle, side="right") - 1)

    def world_state(self, state: State, world: int) -> State:
        """``world``'s part of ``state``: views (writes reach ``state``) at the same time and step."""
        part = self.world_slice(world)
        return State(state.particle_x[part], state.particle_v[part], state.time, step=state.step)

    def particle_name(self, particle: int) -> str:
        if self.world_count == 1:
            return f"particle {particle}"
        w = self.world_of(particle)
        return f"particle {particle} (world {w}, its particle {particle - int(self.world_particle_start[w])})"

    @property
    def bsr_nnz(self) -> int:
        return self.bsr_columns.shape[0]

    def state(self, *, requires_grad: bool | None = None) -> State:
        """A new State at the model's initial positions and velocities."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        return State(
            wp.clone(self.particle_x0, requires_grad=rg),
            wp.clone(self.particle_v0, requires_grad=rg),
        )

    def empty_state(self, *, requires_grad: bool | None = None) -> State:
        """A State whose arrays are allocated but uninitialised, for a step to write into."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        vec3 = self.types.vec3
        return State(
            wp.empty(self.particle_count, dtype=vec3, device=self.device, requires_grad=rg),
            wp.empty(self.particle_count, dtype=vec3, device=self.device, requires_grad=rg),
        )

    def control(self, *, particle_force: bool = False, requires_grad: bool | None = None) -> Control:
        """A Control at the default targets and placements; zero external forces with ``particle_force``."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        vec3 = self.types.vec3
        forces = None
        if particle_force:
            forces = wp.zeros(self.particle_count, dtype=vec3, device=self.device, requires_grad=rg)
        return Control(
            forces,
            wp.array(self.handle_rest_target, dtype=vec3, device=self.device, requires_grad=rg),
            wp.array(self.pin_rest_target, dtype=vec3, device=self.device, requires_grad=rg),
            obstacle_transform=None if self.obstacle_count == 0 else wp.array(
                self.obstacle_rest_transform, dtype=self.types.transform, device=self.device, requires_grad=rg
            ),
        )

    def particle_mass(self) -> np.ndarray:
        """Lumped particle masses [kg] (host), a third of each face's mass per vertex."""
        dens = self.material_density.numpy() * self.material_thicken.numpy()
        face_mass = self.tri_area.numpy() * dens[self.tri_material.numpy()]
        mass = np.zeros(self.particle_count)
        for c in range(3):
            np.add.at(mass, self.triangles_np[:, c], face_mass / 3.0)
        return mass

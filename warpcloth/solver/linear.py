"""The implicit step's linear solve: preconditioned CG on the model's 3x3 block pattern, its adjoint on the tape."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
import warp as wp

from warpcloth.errors import SimulationError
from warpcloth.kernels import status as ks
from warpcloth.kernels.block_matrix import block_matrix_kernels
from warpcloth.kernels.cg_sequential import sequential_cg_kernels
from warpcloth.kernels.cg_tiled import tiled_cg_kernels
from warpcloth.kernels.cg_warp import warp_cg_kernels
from warpcloth.kernels.multigrid import multigrid_kernels
from warpcloth.model import Model
from warpcloth.solver.multigrid import ParallelMultigrid, WorldHierarchies
from warpcloth.solver.options import SolverOptions
from warpcloth.solver.status import Failure, StepStatus
from warpcloth.tape import record_adjoint, untaped

TILED_MAX_PARTICLES = 1024
"""Largest world "auto" gives the tiled CG on CUDA. Why: docs/decisions.md, "Tiled CG up to 1024 particles"."""
_KIND = {"jacobi": 0, "block_jacobi": 1, "block_ssor": 2, "multigrid": 3}  # the CG kernels' preconditioner codes


class SolveInfo(NamedTuple):
    """What one CG solve did."""

    iterations: int
    residual: float
    """Relative residual |b - A x| / |b| (the recursive one of the sequential backend)."""
    converged: bool
    """Whether the residual met the tolerance."""


class LinearSolver:
    """CG for ``A x = b``, A given by its blocks on ``model``'s block pattern; owns its scratch, one solve at a time.
    With ``cg_backend="auto"``, block SSOR asked of a CUDA backend runs as block Jacobi (:attr:`note` says so).

    Args:
        hint: returns text appended to a failed solve's message (e.g. the most elongated triangle).
        status: the failure record the recorded solves latch into; None: a new one.

    Raises:
        ValueError: a preconditioner the chosen backend cannot run, or the multigrid for a world with every particle
            pinned."""

    def __init__(self, model: Model, options: SolverOptions, *, hint: Callable[[], str] | None = None,
                 status: StepStatus | None = None):
        self.model = model
        self.options = options
        self.device = model.device
        self.hint = hint or (lambda: "")
        self.status = status if status is not None else StepStatus(self.device)
        """The failure record and iteration totals the recorded solves write."""
        self.kernels = block_matrix_kernels(model.scalar)
        backend = options.cg_backend
        chosen_by_device = backend == "auto"
        largest = int(np.diff(model.world_particle_start).max())
        if chosen_by_device:
            if self.device.is_cpu:
                backend = "sequential"
            else:  # a thread block per world while a world fits one well; else the many-block warp.optim CG
                backend = "tiled" if largest <= TILED_MAX_PARTICLES else "warp"
                if backend == "warp" and options.preconditioner == "multigrid" and model.world_count > 1:
                    backend = "tiled"  # warp.optim's CG takes the multigrid for one world; the tiled CG for each
        self.backend = backend
        """``"sequential"``, ``"tiled"`` or ``"warp"``: what ``cg_backend`` resolved to on this device."""
        self.note = ""
        """What was mapped to run on this device (empty if nothing was): the CLI prints it."""
        preconditioner = options.preconditioner
        if preconditioner == "auto":
            # a world whose particles are all pinned has nothing to coarsen; the sequential backend runs a hierarchy
            # per world (each world's V-cycle on its thread), the parallel form one hierarchy over one world
            free = model.particle_pin.numpy() < 0
            coarsen = all(free[a:b].any() for a, b in zip(model.world_particle_start[:-1],
                                                         model.world_particle_start[1:]))
            if backend == "tiled":
                preconditioner = "block_jacobi"
            elif backend == "warp":
                preconditioner = "multigrid" if coarsen and model.world_count == 1 else "block_jacobi"
            else:
                preconditioner = "multigrid" if coarsen else "block_ssor"
        if preconditioner == "multigrid" and model.world_count > 1 and backend == "warp":
            raise ValueError(f"SolverOptions.preconditioner 'multigrid' with the {backend} CG backend takes a model "
                             f"of one world (this one has {model.world_count}); the sequential backend runs one "
                             "per world, or use 'block_jacobi'")
        if preconditioner == "block_ssor" and backend != "sequential":
            if not chosen_by_device:
                raise ValueError(f"SolverOptions.preconditioner 'block_ssor' needs cg_backend 'sequential' (its "
                                 f"sweeps are sequential); use 'multigrid' (in parallel form), 'block_jacobi' or "
                                 f"'jacobi' with the {backend} backend")
            self.note = (f"preconditioner {preconditioner!r} is a sequential sweep; the {backend} CG backend that "
                         f"{self.device} runs uses 'block_jacobi' instead")
            preconditioner = "block_jacobi"
        self.preconditioner = preconditioner
        """The preconditioner ``preconditioner`` resolved to."""
        n = model.particle_count
        vec3, mat33 = model.types.vec3, model.types.mat33
        self._scratch = [wp.empty(n, dtype=vec3, device=self.device) for _ in range(4)]
        self._parallel_multigrid = None
        self._mg_scratch = wp.empty(0, dtype=vec3, device=self.device)  # the tiled V-cycle's (multigrid only)
        if preconditioner == "multigrid":
            hierarchy = WorldHierarchies.of_model(model)
            self._multigrid = hierarchy.multigrid(multigrid_kernels(model.scalar), model.scalar, self.device)
            if backend == "warp":  # the same hierarchy in parallel form: Jacobi smoothing, a thread per node
                self._parallel_multigrid = ParallelMultigrid(hierarchy, self._multigrid,
                                                             multigrid_kernels(model.scalar), model, self.device)
            elif backend == "tiled":  # the same parallel form on the threads of each world's block
                self._mg_scratch = wp.zeros(self._multigrid.x.shape[0], dtype=vec3, device=self.device)
            self.multigrid_levels = tuple(hierarchy.sizes)
            """Nodes per level of the multigrid hierarchy over all worlds, the particles first (else empty)."""
        else:
            self._multigrid = multigrid_kernels(model.scalar).Multigrid()  # unused: an empty hierarchy
            self._multigrid.levels = 0
            self.multigrid_levels = ()
        # the block inverses of the diagonal: the particles', then (multigrid) every coarse level's
        self._precond = wp.empty(self._multigrid.b.shape[0] if self._multigrid.levels else n, dtype=mat33,
                                 device=self.device)
        self._world_start = wp.array(model.world_particle_start.astype(np.int32), dtype=wp.int32, device=self.device)
        # per world [iterations, relative residual, converged (0/1)] of the last forward and adjoint solves
        self._info = {which: wp.zeros((model.world_count, 3), dtype=wp.float64, device=self.device)
                      for which in (False, True)}
        self._solved = False
        self._adjoint = wp.zeros(n, dtype=vec3, device=self.device)
        self._warp = None  # the warp backend's matrix, operators and CG functors (_warp_backend)
        self._plain = self.kernels.BlockMatrix()
        self._plain.offsets, self._plain.columns = model.bsr_offsets, model.bsr_columns
        self._plain.diag_slot, self._plain.pair_count = model.particle_diag_slot, 0
        self._plain.pair_world_start = wp.zeros(model.world_count + 1, dtype=wp.int32, device=self.device)
        self._plain.pair_nodes = wp.zeros((0, 4), dtype=wp.int32, device=self.device)
        self._plain.pair_w = wp.zeros(0, dtype=model.types.vec4, device=self.device)
        self._plain.pair_k = wp.zeros(0, dtype=mat33, device=self.device)
        if backend == "warp":  # made here, not at the first solve, which may be inside a graph capture
            self._warp_backend(self._scratch[0], self._scratch[1])
        self.block_dim = options.cg_block_dim or _block_dim(largest, model.world_count)
        """Threads per world of the tiled backend (SolverOptions.cg_block_dim, or chosen from the worlds' sizes)."""

    # -- solves ------------------------------------------------------------------------------------------------------
    def solve(self, values: wp.array, b: wp.array, x: wp.array, *, guess: wp.array | None = None,
              adjoint: bool = False, pairs=None) -> SolveInfo:
        """Solve A x = b (``values`` plus ``pairs``' cross blocks), untaped, from ``guess`` (may be ``x``) or zero;
        reads the device. ``adjoint`` selects ``SolverOptions.adjoint_cg_tol``."""
        self._launch_solve(values, b, x, guess, adjoint, pairs)
        return self.info(adjoint)

    def _launch_solve(self, values, b, x, guess, adjoint: bool, pairs) -> None:
        opt = self.options
        tol = opt.adjoint_cg_tol if adjoint and opt.adjoint_cg_tol is not None else opt.cg_tol
        model = self.model
        self._solved = True
        if self.backend == "warp":
            with untaped():  # its adjoint is the one solve_recorded records
                self._solve_warp(values, b, x, tol, guess, pairs, self._info[adjoint])
            return
        r, z, p, q = self._scratch
        if self.backend == "tiled":
            tiled = tiled_cg_kernels(model.scalar)
            kernel = tiled.cg_tiled_multigrid if self.preconditioner == "multigrid" else tiled.cg_tiled
            wp.launch_tiled(kernel, dim=[model.world_count], block_dim=self.block_dim,
                            device=self.device,
                            inputs=[self.block_matrix(values, pairs), b, float(tol), float(opt.cg_atol),
                                    int(opt.cg_max_iters), _KIND[self.preconditioner], self._multigrid,
                                    model.scalar(ParallelMultigrid.OMEGA), int(guess is not None),
                                    x if guess is None else guess, r, z, p, q, self._mg_scratch, self._precond,
                                    self._world_start],
                            outputs=[x, self._info[adjoint]], record_tape=False)
            return
        wp.launch(sequential_cg_kernels(model.scalar).cg_sequential, model.world_count, device=self.device,
                  inputs=[self.block_matrix(values, pairs), b,
                          float(tol), float(opt.cg_atol), int(opt.cg_max_iters), _KIND[self.preconditioner],
                          model.scalar(opt.ssor_omega), self._multigrid, int(guess is not None),
                          x if guess is None else guess,
                          r, z, p, q, self._precond, self._world_start],
                  outputs=[x, self._info[adjoint]], record_tape=False)

    def info(self, adjoint: bool = False) -> SolveInfo:
        """The last forward (or adjoint) solve: the most iterations of any world, the largest relative residual
        (nan if any is non-finite), and whether every world converged. Reads the device."""
        info = self._info[adjoint].numpy()
        residual = info[:, 1]
        worst = float(np.nan) if not np.all(np.isfinite(residual)) else float(residual.max())
        return SolveInfo(int(info[:, 0].max()), worst, bool(info[:, 2].all()))

    @property
    def world_info(self) -> np.ndarray | None:
        """Per world, the last forward solve's [iterations, relative residual, converged (0/1)], shape
        (world_count, 3) (host copy); None before the first solve. Reads the device."""
        return self._info[False].numpy() if self._solved else None

    def solve_recorded(self, values: wp.array, rhs: wp.array, x: wp.array, *, step: int = 0,
                       guess: wp.array | None = None, adjoint_guess: wp.array | None = None,
                       adjoint_result: wp.array | None = None,
                       after_adjoint: Callable[[], None] | None = None, pairs=None) -> None:
        """Solve A x = b as :meth:`solve` does but without reading the device (failures latch in ``status``), and
        on the active tape record the adjoint: A lam = dL/dx, dL/db += lam, dL/dA_ij -= lam_i x_j^T.

        Args:
            step: the step number that a failed solve's record names.
            adjoint_guess: first guess of the adjoint solve (zeroed once read: a second backward pass repeats the
                first bitwise).
            adjoint_result: receives lam after the adjoint solve.
            pairs: proximity pairs whose cross blocks A has (their adjoint is their own)."""
        self._launch_solve(values, rhs, x, guess, False, pairs)
        self._account(step, adjoint=False)
        if not (values.requires_grad and rhs.requires_grad and x.requires_grad):
            return

        def adjoint():
            lam = self._adjoint
            first = adjoint_guess if self.options.warm_start else None
            self._launch_solve(values, x.grad, lam, first, True, pairs)
            if first is not None:
                first.zero_()
            self._account(step, adjoint=True)
            wp.launch(self.kernels.solve_adjoint_scatter, self.model.particle_count, device=self.device,
                      inputs=[self.block_matrix(values), lam, x],
                      outputs=[values.grad, rhs.grad], record_tape=False)
            if adjoint_result is not None:
                wp.copy(adjoint_result, lam)
            if after_adjoint is not None:
                after_adjoint()

        record_adjoint(adjoint, arrays=[values, rhs, x])

    def _account(self, step: int, adjoint: bool) -> None:
        status = self.status
        wp.launch(ks.account_solve, 1, device=self.device,
                  inputs=[self._info[adjoint], int(step), int(adjoint), int(self.options.on_cg_failure == "raise")],
                  outputs=[status.record, status.detail, status.totals], record_tape=False)

    def block_matrix(self, values: wp.array, pairs=None):
        """The matrix with blocks ``values`` on the model's pattern and the cross blocks of ``pairs`` (a
        :class:`~warpcloth.solver.proximity.ProximityPairs`, or None), as the CG kernels read it."""
        if pairs is None or pairs.count == 0:
            A = self._plain  # built once: a step without pairs only swaps the blocks
        else:
            A = self.kernels.BlockMatrix()
            A.offsets, A.columns, A.diag_slot = self._plain.offsets, self._plain.columns, self._plain.diag_slot
            A.pair_count, A.pair_nodes, A.pair_w, A.pair_k = pairs.count, pairs.nodes, pairs.weights, pairs.stiffness
            A.pair_world_start = pairs.world_start
        if A.values is not values:
            A.values = values
        return A

    # -- failures ----------------------------------------------------------------------------------------------------
    def check(self, info: SolveInfo, which: str, step: int, world: int | None = None) -> None:
        """Warn or raise SimulationError (``on_cg_failure``) for a missed tolerance; raise for a non-finite one."""
        message, fatal = self.failure_message(info, which, step, world)
        if message is not None:
            self._report(message, fatal, world)

    def check_failure(self, failure: Failure, *, cause: str | None = None) -> None:
        """As :meth:`check`, for a failure from the failure record (``cause``: what made it non-finite, if known)."""
        info = SolveInfo(failure.iterations, failure.residual, False)
        which = "adjoint" if failure.adjoint else "forward"
        message, fatal = self.failure_message(info, which, failure.step, failure.index)
        if cause is not None and failure.non_finite:
            message = f"step {failure.step}: {cause} ({message})"
        if failure.count > 1:
            message += f" ({failure.count - 1} more solves missed their tolerance since the last check)"
        self._report(message, fatal, failure.index)

    def _report(self, message: str, fatal: bool, world: int | None) -> None:
        worlds = [world] if world is not None and self.model.world_count > 1 else None
        if fatal:
            raise SimulationError(message, worlds=worlds)
        warnings.warn(message, RuntimeWarning, stacklevel=5)

    def failure_message(self, info: SolveInfo, which: str, step: int, world: int | None) -> tuple[str | None, bool]:
        """(message, whether it raises) for a solve's result, or (None, False) when it succeeded."""
        iters, residual, converged = info
        opt = self.options
        if converged and math.isfinite(residual):
            return None, False
        where = f" in world {world}" if world is not None and self.model.world_count > 1 else ""
        if not math.isfinite(residual):
            grown = ("" if which != "adjoint" else ", or the gradient flowing back outgrew the float type (it can grow "
                     "a few percent a step through long sliding contact: a shorter horizon or dtype=wp.float64)")
            return (f"{which} CG solve of step {step}{where} produced a non-finite residual after {iters} "
                    f"iterations; the system is not positive definite or the state is already invalid{grown}"
                    + self.hint(), True)
        name, tol = "cg_tol", opt.cg_tol
        if which == "adjoint" and opt.adjoint_cg_tol is not None:
            name, tol = "adjoint_cg_tol", opt.adjoint_cg_tol
        return (f"{which} CG solve of step {step}{where} did not converge: relative residual {residual:.3e} "
                f"after {iters} iterations ({name} {tol:g}); raise cg_max_iters or lower dt, or loosen {name} or "
                "use dtype=wp.float64 if float32 rounding is the floor (around 1e-6 on large meshes)"
                + self.hint(), opt.on_cg_failure == "raise")

    # -- the warp backend --------------------------------------------------------------------------------------------
    def _warp_backend(self, b: wp.array, x: wp.array) -> SimpleNamespace:
        """The warp backend's BSR view, operators and CG functors, made before any solve (which may be captured)."""
        if self._warp is not None:
            return self._warp
        import warp.optim.linear as wl
        import warp.sparse as ws

        model, device = self.model, self.device
        n = model.particle_count
        bsr = ws.bsr_zeros(n, n, model.types.mat33, device=device)
        rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(model.bsr_offsets.numpy()))
        ws.bsr_set_from_triplets(
            bsr, wp.array(rows, dtype=wp.int32, device=device), model.bsr_columns,
            wp.zeros(model.bsr_nnz, dtype=model.types.mat33, device=device), prune_numerical_zeros=False)
        if not np.array_equal(bsr.columns.numpy()[: model.bsr_nnz], model.bsr_columns.numpy()):
            raise RuntimeError("warp.sparse reordered the block structure; the slot map would be wrong")
        starts = model.world_particle_start.astype(np.int32)
        batch = None
        if model.world_count > 1:
            batch = dict(batch_offsets=wp.array(3 * starts, dtype=int, device=device),
                         max_batch_length=int(3 * np.diff(starts).max()))
        w = SimpleNamespace(bsr=bsr, batch=batch or {}, functors={}, pairs=None, matrix=self._plain)
        scalar, kernels = model.scalar, warp_cg_kernels(model.scalar)

        def matvec(x, y, z, alpha, beta):  # z = alpha A x + beta y, plus the pairs' cross blocks
            if beta != 0.0 and z.ptr != y.ptr:
                wp.copy(z, y)
            ws.bsr_mv(bsr, x, z, alpha=alpha, beta=beta)
            if w.pairs is not None:
                wp.launch(kernels.pair_product, w.pairs.pair_count, device=device,
                          inputs=[w.pairs, x, scalar(alpha)], outputs=[z], record_tape=False)

        def precondition(x, y, z, alpha, beta):
            if self._parallel_multigrid is not None:
                self._parallel_multigrid.apply(w.matrix, x, y, alpha, beta, z)
                return
            wp.launch(kernels.apply_diagonal, n, device=device,
                      inputs=[self._precond, x, y, scalar(alpha), scalar(beta)], outputs=[z], record_tape=False)

        w.A = wl.LinearOperator(bsr.shape, bsr.dtype, device, matvec, **w.batch)
        w.M = wl.LinearOperator(bsr.shape, bsr.dtype, device, precondition, **w.batch)
        w.template = (b, x)
        self._warp = w
        return w

    def _solve_warp(self, values, b, x, tol: float, guess: wp.array | None, pairs, info: wp.array) -> None:
        """``warp.optim.linear.cg``, pairs matrix-free; convergence tested on the device on CUDA, else on the host
        (every world then reports the worst world's residual)."""
        import warp.optim.linear as wl

        model, opt = self.model, self.options
        w = self._warp_backend(b, x)
        w.bsr.values = values
        matrix = self.block_matrix(values, pairs)
        w.matrix = matrix  # the preconditioner's level 0 (the multigrid smooths the pattern's blocks alone)
        w.pairs = matrix if matrix.pair_count else None
        if guess is None:
            x.zero_()
        elif guess is not x:
            wp.copy(x, guess)
        if self._parallel_multigrid is not None:
            self._parallel_multigrid.setup(matrix)
        else:
            wp.launch(warp_cg_kernels(model.scalar).diagonal_inverse, model.particle_count, device=self.device,
                      inputs=[matrix, int(self.preconditioner != "jacobi")],
                      outputs=[self._precond], record_tape=False)
        device_side = self.device.is_cuda
        key = (tol, opt.cg_atol, opt.cg_max_iters)
        if key not in w.functors:
            w.functors[key] = wl.cg(w.A, *w.template, tol=tol, atol=opt.cg_atol, maxiter=opt.cg_max_iters, M=w.M,
                                    check_every=0 if device_side else 1, use_cuda_graph=True, run=False)
        result = w.functors[key](b=b, x=x)
        if device_side:
            iterations, r_norm_sq, atol_sq = result
            wp.launch(warp_cg_kernels(model.scalar).warp_cg_info, model.world_count, device=self.device,
                      inputs=[iterations, r_norm_sq, atol_sq, float(tol)], outputs=[info], record_tape=False)
        else:  # host results: the worst world's residual and threshold
            iterations, residual, threshold = result
            relative = float(residual) * tol / max(float(threshold), 1e-300)
            row = [float(iterations), relative, float(residual <= threshold)]
            info.assign(np.tile(np.array(row, dtype=np.float64), (model.world_count, 1)))


def _block_dim(largest_world: int, worlds: int) -> int:
    """Threads per world of the tiled CG: a power of two in [64, 256], two rows a thread below 128 worlds.
    Why: docs/decisions.md, "Tiled CG block sizes"."""
    rows = largest_world if worlds >= 128 else (largest_world + 1) // 2
    return int(min(256, max(64, 1 << max(0, rows - 1).bit_length())))

"""The linear solve of the implicit step: preconditioned CG on the model's fixed 3x3 block pattern, and its
implicit adjoint (one adjoint solve with the same matrix, SPEC.md §4.1) recorded on the tape instead of the CG
iterations."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import warp as wp

from warpcloth.errors import SimulationError
from warpcloth.kernels.linear import linear_kernels
from warpcloth.model import Model
from warpcloth.solver.multigrid import Hierarchy
from warpcloth.solver.options import SolverOptions
from warpcloth.tape import record_adjoint, untaped


class SolveInfo(NamedTuple):
    """What one CG solve did."""

    iterations: int
    residual: float
    """Relative residual |b - A x| / |b| (the recursive one of the sequential backend)."""
    converged: bool
    """Whether the residual met the tolerance."""


class LinearSolver:
    """CG for ``A x = b`` where A is given by its blocks on ``model``'s block pattern (``bsr_offsets``,
    ``bsr_columns``). Owns its scratch; one solve at a time.

    Args:
        model: the Model whose block pattern the systems use.
        options: SolverOptions (tolerances, preconditioner, backend, what a failed solve does).
        hint: returns text appended to a failed solve's message (e.g. the most elongated triangle).
    """

    def __init__(self, model: Model, options: SolverOptions, *, hint: Callable[[], str] | None = None):
        self.model = model
        self.options = options
        self.device = model.device
        self.hint = hint or (lambda: "")
        self.kernels = linear_kernels(model.scalar)
        backend = options.cg_backend
        if backend == "auto":
            backend = "sequential" if self.device.is_cpu else "warp"
        self.backend = backend
        """``"sequential"`` or ``"warp"``: the backend ``cg_backend`` resolved to on this device."""
        preconditioner = options.preconditioner
        if preconditioner == "auto":
            if backend != "sequential":
                preconditioner = "block_jacobi"
            else:  # a model whose particles are all pinned has nothing to coarsen; one hierarchy spans one world
                free = (model.particle_pin.numpy() < 0).any()
                preconditioner = "multigrid" if free and model.world_count == 1 else "block_ssor"
        if preconditioner == "multigrid" and model.world_count > 1:
            raise ValueError(f"SolverOptions.preconditioner 'multigrid' takes a model of one world (this one has "
                             f"{model.world_count}); use 'block_ssor', which each world's solve runs on its own")
        if preconditioner in ("block_ssor", "multigrid") and backend != "sequential":
            raise ValueError(f"SolverOptions.preconditioner {preconditioner!r} needs cg_backend 'sequential' (its "
                             "sweeps are sequential); use 'block_jacobi' or 'jacobi' with the warp backend")
        self.preconditioner = preconditioner
        """The preconditioner ``preconditioner`` resolved to."""
        n = model.particle_count
        vec3, mat33 = model.types.vec3, model.types.mat33
        self._scratch = [wp.empty(n, dtype=vec3, device=self.device) for _ in range(4)]
        if preconditioner == "multigrid":
            hierarchy = Hierarchy(model.bsr_offsets.numpy(), model.bsr_columns.numpy(), model.tri_indices.numpy(),
                                  model.particle_pin.numpy() >= 0)
            self._multigrid = hierarchy.multigrid(self.kernels, model.scalar, self.device)
            self.multigrid_levels = tuple(hierarchy.sizes)
            """Nodes per level of the multigrid hierarchy, the particles first (empty without multigrid)."""
        else:
            self._multigrid = self.kernels.Multigrid()  # unused: an empty hierarchy
            self._multigrid.levels = 0
            self.multigrid_levels = ()
        # the block inverses of the diagonal: the particles', then (multigrid) every coarse level's
        self._precond = wp.empty(self._multigrid.b.shape[0] if self._multigrid.levels else n, dtype=mat33,
                                 device=self.device)
        self._world_start = wp.array(model.world_particle_start.astype(np.int32), dtype=wp.int32, device=self.device)
        self._info = wp.zeros((model.world_count, 3), dtype=wp.float64, device=self.device)
        # on the CPU the host view shares memory: reading it costs no copy and no launch
        self._info_host = self._info.numpy() if self.device.is_cpu else None
        self.world_info: np.ndarray | None = None
        """Per world, the last sequential solve's [iterations, relative residual, converged (0/1)], shape
        (world_count, 3) (host); the SolveInfo it returns holds the most iterations, the largest residual and
        whether every world converged. None before the first solve, and with the warp backend."""
        self._adjoint = wp.zeros(n, dtype=vec3, device=self.device)
        self._warp_matrix = None
        self._plain = self.kernels.BlockMatrix()
        self._plain.offsets, self._plain.columns = model.bsr_offsets, model.bsr_columns
        self._plain.diag_slot, self._plain.pair_count = model.particle_diag_slot, 0
        self._plain.pair_world_start = wp.zeros(model.world_count + 1, dtype=wp.int32, device=self.device)
        self._plain.pair_nodes = wp.zeros((0, 4), dtype=wp.int32, device=self.device)
        self._plain.pair_w = wp.zeros(0, dtype=model.types.vec4, device=self.device)
        self._plain.pair_k = wp.zeros(0, dtype=mat33, device=self.device)

    def solve(self, values: wp.array, b: wp.array, x: wp.array, *, guess: wp.array | None = None,
              adjoint: bool = False, pairs=None) -> SolveInfo:
        """Solve A x = b from the first guess ``guess`` (which may be ``x`` itself), or from zero. Not taped.

        A is ``values`` on the model's block pattern plus the cross blocks of proximity ``pairs`` (if any);
        ``adjoint`` selects the adjoint tolerance (``SolverOptions.adjoint_cg_tol``).
        """
        opt = self.options
        tol = opt.adjoint_cg_tol if adjoint and opt.adjoint_cg_tol is not None else opt.cg_tol
        model = self.model
        if self.backend == "warp":
            with untaped():  # its adjoint is the one solve_recorded records
                return self._solve_warp(values, b, x, tol, guess, pairs)
        kind = {"jacobi": 0, "block_jacobi": 1, "block_ssor": 2, "multigrid": 3}[self.preconditioner]
        r, z, p, q = self._scratch
        wp.launch(self.kernels.cg_sequential, model.world_count, device=self.device,
                  inputs=[self.block_matrix(values, pairs), b,
                          float(tol), float(opt.cg_atol), int(opt.cg_max_iters), kind,
                          model.scalar(opt.ssor_omega), self._multigrid, int(guess is not None),
                          x if guess is None else guess,
                          r, z, p, q, self._precond, self._world_start],
                  outputs=[x, self._info], record_tape=False)
        info = self._info_host if self._info_host is not None else self._info.numpy()
        self.world_info = info
        if model.world_count == 1:
            return SolveInfo(int(info[0, 0]), float(info[0, 1]), bool(info[0, 2]))
        residual = info[:, 1]
        worst = float(np.nan) if not np.all(np.isfinite(residual)) else float(residual.max())
        return SolveInfo(int(info[:, 0].max()), worst, bool(info[:, 2].all()))

    def solve_recorded(self, values: wp.array, rhs: wp.array, x: wp.array, *, step: int = 0,
                       guess: wp.array | None = None, adjoint_guess: wp.array | None = None,
                       adjoint_result: wp.array | None = None,
                       on_adjoint: Callable[[SolveInfo], None] | None = None, pairs=None) -> SolveInfo:
        """Solve A x = b (as :meth:`solve`), check it, and on the active tape record the implicit adjoint:
        A lam = dL/dx, dL/db += lam, dL/dA_ij -= lam_i x_j^T on the stored blocks.

        Args:
            step: the step number that a failed solve's message names.
            guess: first guess of the forward solve.
            adjoint_guess: first guess of the adjoint solve (read once, then zeroed, so a second backward pass
                over the same tape repeats the first bitwise).
            adjoint_result: receives lam after the adjoint solve (the next adjoint solve's first guess).
            on_adjoint: called with the adjoint solve's SolveInfo (statistics).
            pairs: proximity pairs whose cross blocks A has (their adjoint is the pairs' own, proximity.py).
        """
        info = self.solve(values, rhs, x, guess=guess, pairs=pairs)
        self.check(info, "forward", step)
        if not (values.requires_grad and rhs.requires_grad and x.requires_grad):
            return info

        def adjoint():
            lam = self._adjoint
            first = adjoint_guess if self.options.warm_start else None
            result = self.solve(values, x.grad, lam, guess=first, adjoint=True, pairs=pairs)
            if first is not None:
                first.zero_()
            if on_adjoint is not None:
                on_adjoint(result)
            self.check(result, "adjoint", step)
            wp.launch(self.kernels.solve_adjoint_scatter, self.model.particle_count, device=self.device,
                      inputs=[self.block_matrix(values), lam, x],
                      outputs=[values.grad, rhs.grad], record_tape=False)
            if adjoint_result is not None:
                wp.copy(adjoint_result, lam)

        record_adjoint(adjoint, arrays=[values, rhs, x])
        return info

    def block_matrix(self, values: wp.array, pairs=None):
        """The matrix with blocks ``values`` on the model's pattern and the cross blocks of ``pairs`` (a
        :class:`~warpcloth.collision.proximity.ProximityPairs`, or None), as the CG kernels read it."""
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

    def check(self, info: SolveInfo, which: str, step: int) -> None:
        """Warn or raise (``SolverOptions.on_cg_failure``) when a solve missed its tolerance; always raise on a
        non-finite residual."""
        iters, residual, converged = info
        opt = self.options
        world, worlds = "", None
        if self.model.world_count > 1 and self.world_info is not None and not (converged and math.isfinite(residual)):
            w = self._failed_world()
            world, worlds = f" in world {w}", [w]
            iters, residual = int(self.world_info[w, 0]), float(self.world_info[w, 1])
        if not math.isfinite(residual):
            raise SimulationError(f"{which} CG solve of step {step}{world} produced a non-finite residual after "
                                  f"{iters} iterations; the system is not positive definite or the state is already "
                                  "invalid"
                                  + self.hint(), worlds=worlds)
        if not converged:
            name, tol = "cg_tol", opt.cg_tol
            if which == "adjoint" and opt.adjoint_cg_tol is not None:
                name, tol = "adjoint_cg_tol", opt.adjoint_cg_tol
            msg = (f"{which} CG solve of step {step}{world} did not converge: relative residual {residual:.3e} "
                   f"after {iters} iterations ({name} {tol:g}); raise cg_max_iters or lower dt, or loosen {name} or "
                   "use dtype=wp.float64 if float32 rounding is the floor (around 1e-6 on large meshes)"
                   + self.hint())
            if opt.on_cg_failure == "raise":
                raise SimulationError(msg, worlds=worlds)
            warnings.warn(msg, RuntimeWarning, stacklevel=4)

    def _failed_world(self) -> int:
        """The world of the last solve with a non-finite residual, else the one with the largest residual."""
        residual = self.world_info[:, 1]
        bad = np.flatnonzero(~np.isfinite(residual))
        return int(bad[0]) if bad.size else int(np.argmax(residual))

    def _solve_warp(self, values, b, x, tol: float, guess: wp.array | None, pairs) -> SolveInfo:
        """``warp.optim.linear.cg`` on a BSR view of ``values`` (the CUDA path), plus the pairs' cross blocks as a
        matrix-free term of the operator (one launch per product, a thread per pair)."""
        import warp.optim.linear as wl
        import warp.sparse as ws

        model = self.model
        if self._warp_matrix is None:
            A = ws.bsr_zeros(model.particle_count, model.particle_count, model.types.mat33, device=self.device)
            rows = np.repeat(np.arange(model.particle_count, dtype=np.int32), np.diff(model.bsr_offsets.numpy()))
            ws.bsr_set_from_triplets(
                A, wp.array(rows, dtype=wp.int32, device=self.device), model.bsr_columns,
                wp.zeros(model.bsr_nnz, dtype=model.types.mat33, device=self.device), prune_numerical_zeros=False)
            if not np.array_equal(A.columns.numpy()[: model.bsr_nnz], model.bsr_columns.numpy()):
                raise RuntimeError("warp.sparse reordered the block structure; the slot map would be wrong")
            self._warp_matrix = A
        A = self._warp_matrix
        A.values = values
        if guess is None:
            x.zero_()
        elif guess is not x:
            wp.copy(x, guess)
        # the pairs' own blocks are on the diagonal: the preconditioner of the BSR part is theirs too
        M = wl.preconditioner(A, "block_jacobi_direct" if self.preconditioner == "block_jacobi" else "diag")
        if pairs is not None and pairs.count:
            A = self._with_pairs(A, self.block_matrix(values, pairs), pairs.count)
        opt = self.options
        # warp's cg tests |r| <= max(tol |b|, atol); check_every=1 reports the exact iteration count
        iters, residual, threshold = wl.cg(A, b, x, tol=tol, atol=opt.cg_atol, maxiter=opt.cg_max_iters,
                                           M=M, check_every=1, use_cuda_graph=False)
        bnorm = float(np.linalg.norm(b.numpy()))
        return SolveInfo(int(iters), float(residual) / max(bnorm, 1e-300), bool(residual <= threshold))

    def _with_pairs(self, bsr, matrix, count: int):
        """A warp LinearOperator for the BSR blocks plus the ``count`` pairs' cross blocks of ``matrix``."""
        import warp.optim.linear as wl
        import warp.sparse as ws

        kernel, device, scalar = self.kernels.pair_product, self.device, self.model.scalar

        def matvec(x, y, z, alpha, beta):
            # z = alpha A x + beta y
            if beta != 0.0 and z.ptr != y.ptr:
                wp.copy(z, y)
            ws.bsr_mv(bsr, x, z, alpha=alpha, beta=beta)
            wp.launch(kernel, count, device=device, inputs=[matrix, x, scalar(alpha)], outputs=[z],
                      record_tape=False)

        return wl.LinearOperator(bsr.shape, bsr.dtype, device, matvec)

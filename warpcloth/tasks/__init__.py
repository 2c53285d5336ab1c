"""Applications written against the public API (``warpcloth``, ``warpcloth.kernels``): inverse problems.

* ``control``: motion control, ``ControlTask`` (pushes on chosen particles, a centre-of-mass or target-position loss;
  from a scene's ``[control]`` table with ``ControlTask.from_scene``).
* ``controllers``: its optimisers: damped Gauss-Newton or L-BFGS on the pushes, the global searches over worlds
  (a multistart in lockstep, CMA-ES), and a PyTorch MLP controller trained through the simulator.
* ``estimation``: material estimation, ``EstimationTask`` (from a scene's ``[estimate]`` table with
  ``EstimationTask.from_scene``), fitting a fabric's density, stretching and bending to a trajectory.
* ``throw``: the seed's throw into a basket (the embedded scene ``basket-throw``) and its published figures.
* ``scenes``: the seed's scenes built in code: the hanging cloth in the wind (any mesh, handles, lagged normals) and
  other motions of a fabric, and the throw's scene.
* ``optim``: the algorithms both kinds of task use on a NumPy parameter vector: L-BFGS, Adam, CMA-ES over a
  population evaluated as one batch, and the Gaussian-smoothed gradient from perturbed copies.
* ``lockstep``: several optimisations in threads whose requests run as one batch of worlds.

Their loss kernels live in ``warpcloth.kernels.losses``.
"""

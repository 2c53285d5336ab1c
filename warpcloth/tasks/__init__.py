"""Applications written against the public API (``warpcloth``, ``warpcloth.kernels``): inverse problems.

* ``control``: motion control, ``ControlTask`` (pushes on chosen particles, a centre-of-mass or target-position loss;
  from a scene's ``[control]`` table with ``ControlTask.from_scene``) and its optimisers (damped Gauss-Newton or
  L-BFGS on the pushes, or a PyTorch MLP controller).
* ``estimation``: material estimation, ``EstimationTask`` (from a scene's ``[estimate]`` table with
  ``EstimationTask.from_scene``), fitting a fabric's density, stretching and bending to a trajectory.
* ``throw``: the seed's throw into a basket (the embedded scene ``basket-throw``) and its published figures.
* ``scenes``: the seed's scenes built in code: the hanging cloth in the wind (any mesh, handles, lagged normals) and
  other motions of a fabric, and the throw's scene.
* ``optim``: the small optimisers they use (L-BFGS, Adam) on a NumPy parameter vector.

Their loss kernels live in ``warpcloth.kernels.losses``.
"""

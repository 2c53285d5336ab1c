"""Applications written against the public API (``warpcloth``, ``warpcloth.kernels``): the seed's inverse problems.

* ``scenes``: the seed's scenes, built once: the hanging cloth in the wind and the throw over a wall into a basket.
* ``estimation``: material estimation, fitting a fabric's density, stretching and bending to a trajectory.
* ``throw``: motion control, corner pushes (open-loop or a PyTorch MLP) that throw the cloth into the basket.
* ``optim``: the small optimisers they use (L-BFGS, Adam) on a NumPy parameter vector.

Their loss kernels live in ``warpcloth.kernels.losses``.
"""

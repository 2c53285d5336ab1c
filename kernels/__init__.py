"""Warp device code for warpcloth: ``@wp.func`` physics and thin ``@wp.kernel`` loops.

Every module exposes cached factories keyed by the scalar type (``wp.float32`` or ``wp.float64``), so one
source serves both precisions; nothing here allocates or launches.
"""

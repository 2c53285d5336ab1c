"""Vector and matrix types for one scalar precision."""

import functools
from types import SimpleNamespace

import warp as wp


@functools.cache
def types(scalar):
    """Return the vec/mat types used by the kernels for ``scalar`` (``wp.float32`` or ``wp.float64``)."""
    return SimpleNamespace(
        scalar=scalar,
        vec2=wp.types.vector(2, scalar),
        vec3=wp.types.vector(3, scalar),
        vec4=wp.types.vector(4, scalar),
        mat22=wp.types.matrix((2, 2), scalar),
        mat33=wp.types.matrix((3, 3), scalar),
        quat=wp.quatd if scalar == wp.float64 else wp.quatf,
        transform=wp.transformd if scalar == wp.float64 else wp.transformf,
    )


def per_precision(factory):
    """Decorate a kernel factory ``factory(scalar)``: cached, and built for both precisions when its module is
    imported, so the module's hash (and with it its kernel cache entry) never changes with what ran first."""
    cached = functools.cache(factory)
    for scalar in (wp.float32, wp.float64):
        cached(scalar)
    return cached

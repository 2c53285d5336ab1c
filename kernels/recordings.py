"""Synthetic recordings' visibility test: a ray from the camera to each point through a ``wp.Mesh`` of the cloth and
its obstacles (single precision, as ``wp.Mesh`` is)."""

import warp as wp


# seen[i] = 1 when nothing of the mesh lies on the segment from the eye to points[i], short of the point by more
# than tolerance [m]; both sides of every triangle occlude (a cloth is thin: its back is a surface too)
@wp.kernel
def unoccluded(mesh: wp.uint64, eye: wp.vec3, points: wp.array(dtype=wp.vec3), tolerance: float,
               seen: wp.array(dtype=wp.int32)):
    i = wp.tid()
    d = points[i] - eye
    distance = wp.length(d)
    seen[i] = 0
    if distance > tolerance:
        if not wp.mesh_query_ray_anyhit(mesh, eye, d / distance, distance - tolerance):
            seen[i] = 1

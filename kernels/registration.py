"""Registration's closest-point query: each recorded point's closest point on a template's ``wp.Mesh`` (single
precision, as ``wp.Mesh`` is); off the tape, the host code solves the least-squares steps."""

import warp as wp


# face[i], bary[i]: the face of the mesh closest to points[i] and the closest point's barycentric coordinates on its
# corners in their order (wp.mesh_eval_position's u, v, 1 - u - v); face -1 where the query found nothing
@wp.kernel
def closest_points(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), face: wp.array(dtype=wp.int32),
                   bary: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    hit = wp.mesh_query_point_no_sign(mesh, points[i], 1.0e30)
    f = int(-1)
    b = wp.vec3(0.0, 0.0, 0.0)
    if hit.result:
        f = hit.face
        b = wp.vec3(hit.u, hit.v, 1.0 - hit.u - hit.v)
    face[i] = f
    bary[i] = b


# nearest[i]: the index of the row of points nearest to queries[i] (brute force: a template's vertices against a
# point cloud, both small)
@wp.kernel
def nearest_points(queries: wp.array(dtype=wp.vec3), points: wp.array(dtype=wp.vec3),
                   nearest: wp.array(dtype=wp.int32)):
    i = wp.tid()
    q = queries[i]
    best = float(1.0e30)
    k = int(0)
    for j in range(points.shape[0]):
        d = wp.length_sq(points[j] - q)
        if d < best:
            best = d
            k = j
    nearest[i] = k

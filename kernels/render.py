"""The preview's ray caster: one ray a pixel through a ``wp.Mesh`` of the cloth and its obstacles, shaded (single
precision only: a picture needs no more)."""

import warp as wp

AMBIENT, KEY, FILL = wp.constant(0.22), wp.constant(0.5), wp.constant(0.28)  # light: everywhere, lamp, headlight
SHADOWED = wp.constant(0.3)  # share of the lamp's light left in a shadow
LAYERS = wp.constant(6)  # surfaces a ray passes through at most


# ids[i, j]: the first hit's object (-1 background, 0 cloth, k + 1 obstacle k); rgb[i, j]: the shaded colour over
# what it holds (the background), through translucent layers front to back
@wp.kernel
def ray_cast(mesh: wp.uint64, eye: wp.vec3, forward: wp.vec3, right: wp.vec3, up: wp.vec3, window: wp.vec4,
             light: wp.vec3, eps: float, face_object: wp.array(dtype=wp.int32),
             corner_normal: wp.array(dtype=wp.vec3), palette: wp.array(dtype=wp.vec3),
             alpha: wp.array(dtype=float), rgb: wp.array2d(dtype=wp.vec3), ids: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    x = window[0] + (float(j) + 0.5) / float(rgb.shape[1]) * (window[1] - window[0])
    y = window[3] - (float(i) + 0.5) / float(rgb.shape[0]) * (window[3] - window[2])
    d = wp.normalize(forward + x * right + y * up)
    start = eye
    color = wp.vec3(0.0)
    through = float(1.0)  # noqa: UP018 (a Warp variable the loop changes); the share still to show behind
    first = int(-1)  # noqa: UP018
    for layer in range(LAYERS):  # front to back, through translucent surfaces
        hit = wp.mesh_query_ray(mesh, start, d, 1.0e30)
        if not hit.result:
            break
        obj = face_object[hit.face]
        if layer == 0:
            first = obj
        c = hit.face * 3
        n = wp.normalize(hit.u * corner_normal[c] + hit.v * corner_normal[c + 1]
                    + (1.0 - hit.u - hit.v) * corner_normal[c + 2])
        base = palette[obj + 1]
        if wp.dot(hit.normal, d) > 0.0:  # the back of the face: shade the side the camera sees
            n = -n
            if obj == 0:
                base = palette[0]
        lit = wp.dot(n, light)
        shade = AMBIENT + FILL * wp.max(-wp.dot(n, d), 0.0)
        p = start + hit.t * d
        if lit > 0.0:
            if wp.mesh_query_ray_anyhit(mesh, p + n * eps, light, 1.0e30):
                lit = lit * SHADOWED
            shade = shade + KEY * lit
        color = color + (through * alpha[obj] * shade) * base
        through = through * (1.0 - alpha[obj])
        if through < 0.01:
            break
        start = p + eps * d
    ids[i, j] = first
    rgb[i, j] = color + through * rgb[i, j]

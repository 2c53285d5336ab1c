"""Collision detection kernels (vertex-face and edge-edge, CCD and proximity) and the contact geometry."""

import numpy as np
import pytest
import warp as wp

from warpcloth.collision.detection import RowSort
from warpcloth.kernels import collision as kc
from warpcloth.kernels.collision import collision_kernels
from warpcloth.kernels.contact import EE_DIRECTION, EE_PLANE, VF_PLANE, contact_kernels
from warpcloth.kernels.geometry import world_starts

DELTA = 5e-4


def _detect(x0, x1, queries, targets, kind, *, flag=0, capacity=64, dtype=wp.float64, reference=None,
            keep_start_gaps=0):
    """Run the detection kernel (kernels/collision.py query_all) with one query on node positions x0 -> x1
    (``reference``: the positions that side a pair touching at the start, default x1); returns (count, nodes, mode,
    t, sign)."""
    k = collision_kernels(dtype)
    vec3 = wp.types.vector(3, dtype)
    X0 = wp.array(x0, dtype=vec3)
    X1 = wp.array(x1, dtype=vec3)
    XR = X1 if reference is None else wp.array(reference, dtype=vec3)
    q = wp.array(np.asarray(queries, dtype=np.int32).reshape(len(queries), -1), dtype=wp.int32)
    tg = wp.array(np.asarray(targets, dtype=np.int32), dtype=wp.int32)
    bounds = []
    for prims in (q, tg):
        lo = wp.zeros(prims.shape[0], dtype=wp.vec3)
        hi = wp.zeros(prims.shape[0], dtype=wp.vec3)
        wp.launch(k.primitive_bounds, prims.shape[0], inputs=[X0, X1, wp.zeros(1, dtype=wp.vec3),
                                                              wp.zeros(len(x0), dtype=wp.int32), prims,
                                                              prims.shape[1], 0.5 * DELTA], outputs=[lo, hi])
        bounds.append((lo, hi))
    bvh = wp.Bvh(*bounds[1])
    count = wp.zeros(1, dtype=wp.int32)
    nodes = wp.zeros((capacity, 4), dtype=wp.int32)
    mode = wp.zeros(capacity, dtype=wp.int32)
    t = wp.zeros(capacity, dtype=wp.float64)
    sign = wp.zeros(capacity, dtype=wp.float64)
    rows = np.asarray(queries, dtype=np.int32).reshape(len(queries), -1)
    rows = wp.array(np.repeat(rows, 2, axis=1) if kind == "vf" else rows, dtype=wp.int32)  # a vertex as (v, v)
    ints = lambda *values: wp.array(values, dtype=int)  # noqa: E731
    wp.launch(k.query_all, q.shape[0],
              inputs=[X0, X1, XR, rows, tg, bounds[0][0], bounds[0][1], ints(0, q.shape[0]), ints(0),
                      wp.array([bvh.id], dtype=wp.uint64), ints(0), ints(int(kind == "vf")), ints(flag),
                      wp.float64(DELTA), wp.array([keep_start_gaps], dtype=wp.int32), capacity,
                      wp.zeros(len(x0), dtype=wp.int32), 0, wp.zeros(1, dtype=wp.int32)],
              outputs=[count, wp.zeros(2 * capacity, dtype=wp.int64), wp.zeros(2 * capacity, dtype=wp.int32), nodes,
                       mode, t, sign])
    c = int(count.numpy()[0])
    m = min(c, capacity)
    return c, nodes.numpy()[:m], mode.numpy()[:m], t.numpy()[:m], sign.numpy()[:m]


def _geometry(x0, x1, nodes, mode, t, sign, dtype=wp.float64, keep_start_gaps=0, targets=False):
    k = contact_kernels(dtype)
    vec3 = wp.types.vector(3, dtype)
    vec4 = wp.types.vector(4, dtype)
    m = len(mode)
    n_out = wp.zeros(m, dtype=vec3)
    w_out = wp.zeros(m, dtype=vec4)
    target = wp.zeros(m, dtype=dtype)
    wp.launch(k.geometry, m, inputs=[wp.array(x0, dtype=vec3), wp.array(x1, dtype=vec3),
                                     wp.array(nodes, dtype=wp.int32), wp.array(mode, dtype=wp.int32),
                                     wp.array(t, dtype=dtype), wp.array(sign, dtype=dtype), dtype(DELTA),
                                     wp.array([keep_start_gaps], dtype=wp.int32),
                                     wp.zeros(len(x0), dtype=wp.int32)],
              outputs=[n_out, w_out, target])
    if targets:
        return n_out.numpy(), w_out.numpy(), target.numpy()
    return n_out.numpy(), w_out.numpy()


def _constraint(x, nodes, n, w):
    """sum_k w_k n . x_k per contact: the separation the projection keeps >= thickness."""
    return np.einsum("ma,mc,mac->m", w, n, x[nodes])


TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@pytest.mark.parametrize("dtype", [wp.float32, wp.float64])
def test_vertex_crossing_a_face_is_found_with_time_and_side(dtype):
    # vertex 3 falls from z = 0.1 to z = -0.3 through the face: crossing at t = 0.25, from the +z side
    x0 = np.vstack([TRI, [0.2, 0.2, 0.1]])
    x1 = np.vstack([TRI, [0.2, 0.2, -0.3]])
    c, nodes, mode, t, sign = _detect(x0, x1, [3], [[0, 1, 2]], "vf", dtype=dtype)
    assert c == 1 and mode[0] == VF_PLANE and nodes[0].tolist() == [3, 0, 1, 2]
    assert t[0] == pytest.approx(0.25, abs=1e-9 if dtype == wp.float64 else 1e-7)  # float32 inputs
    n, w = _geometry(x0, x1, nodes, mode, t.astype(np.float64), sign)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0], atol=1e-12)  # points to where the vertex came from
    np.testing.assert_allclose(w[0], [1.0, -0.6, -0.2, -0.2], atol=1e-12)
    # the constraint is violated at the end (-0.3 < delta): the projection will lift the vertex
    assert _constraint(x1, nodes, n, w)[0] == pytest.approx(-0.3)


def test_vertex_near_a_face_from_below_gets_a_downward_normal():
    x0 = np.vstack([TRI, [0.3, 0.3, -0.01]])
    x1 = np.vstack([TRI, [0.3, 0.3, -0.2 * DELTA]])
    c, nodes, mode, t, sign = _detect(x0, x1, [3], [[0, 1, 2]], "vf")
    assert c == 1 and t[0] == 1.0 and sign[0] == -1.0
    n, w = _geometry(x0, x1, nodes, mode, t, sign)
    np.testing.assert_allclose(n[0], [0.0, 0.0, -1.0], atol=1e-12)
    assert _constraint(x1, nodes, n, w)[0] == pytest.approx(0.2 * DELTA)


def test_vertex_touching_a_face_at_the_start_takes_its_side_from_the_reference():
    # A vertex in the face's plane at the start (a triangle folded flat onto its neighbour) has no start side: the
    # reference positions (the step's unprojected end, the same in every round) give it, whatever this round's end.
    for sign_noise in (1e-14, -1e-14):  # rounding noise either way must not decide
        x0 = np.vstack([TRI, [0.3, 0.3, sign_noise]])
        reference = np.vstack([TRI, [0.3, 0.3, 0.2 * DELTA]])  # above
        for end_z in (0.2 * DELTA, -0.2 * DELTA, -0.01):  # proximity above, proximity below, crossing or leaving
            x1 = np.vstack([TRI, [0.3, 0.3, end_z]])
            c, nodes, mode, t, sign = _detect(x0, x1, [3], [[0, 1, 2]], "vf", reference=reference)
            crossing = sign_noise > 0 and end_z < 0  # a vertex starting just below and moving down touches nothing
            assert c == (1 if abs(end_z) < DELTA or crossing else 0), (sign_noise, end_z)
            if c:
                assert sign[0] == 1.0, (sign_noise, end_z)
        below = np.vstack([TRI, [0.3, 0.3, -0.2 * DELTA]])
        c, nodes, mode, t, sign = _detect(x0, below, [3], [[0, 1, 2]], "vf", reference=below)
        assert c == 1 and sign[0] == -1.0


def test_far_or_outside_vertices_are_not_contacts():
    x0 = np.vstack([TRI, [0.3, 0.3, 0.1], [2.0, 2.0, 1e-4], [0.3, 0.3, 3 * DELTA]])
    x1 = x0.copy()
    c, *_ = _detect(x0, x1, [3, 4, 5], [[0, 1, 2]], "vf")
    assert c == 0


def test_fast_vertex_does_not_tunnel_through_a_thin_plate():
    # 20 m/s for 0.02 s: 0.4 m in one step through a plate of two triangles
    plate = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    x0 = np.vstack([plate, [0.1, 0.05, 0.2]])
    x1 = np.vstack([plate, [0.1, 0.05, -0.2]])
    c, nodes, mode, t, sign = _detect(x0, x1, [4], [[0, 1, 2], [0, 2, 3]], "vf")
    assert c >= 1 and np.all(t == pytest.approx(0.5))


def test_moving_face_hits_resting_vertex():
    # the face moves up through a vertex at rest: relative motion decides the side (vertex ends below)
    x0 = np.vstack([TRI - [0, 0, 0.1], [0.2, 0.2, 0.0]])
    x1 = np.vstack([TRI + [0, 0, 0.1], [0.2, 0.2, 0.0]])
    c, nodes, mode, t, sign = _detect(x0, x1, [3], [[0, 1, 2]], "vf")
    assert c == 1 and t[0] == pytest.approx(0.5)
    n, w = _geometry(x0, x1, nodes, mode, t, sign)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0], atol=1e-12)
    assert _constraint(x1, nodes, n, w)[0] == pytest.approx(-0.1)


def test_crossing_edges_are_found():
    # edge (0,1) along x at z = 0.1 moving down through edge (2,3) along y at z = 0
    x0 = np.array([[-1.0, 0.3, 0.1], [1.0, 0.3, 0.1], [0.2, -1.0, 0.0], [0.2, 1.0, 0.0]])
    x1 = x0.copy()
    x1[:2, 2] -= 0.4
    c, nodes, mode, t, sign = _detect(x0, x1, [[0, 1]], [[2, 3]], "ee")
    assert c == 1 and mode[0] == EE_PLANE and t[0] == pytest.approx(0.25)
    n, w = _geometry(x0, x1, nodes, mode, t, sign)
    np.testing.assert_allclose(np.abs(n[0]), [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(w[0], [0.4, 0.6, -0.35, -0.65], atol=1e-12)
    assert n[0][2] > 0  # edge (0,1) came from above
    assert _constraint(x1, nodes, n, w)[0] == pytest.approx(-0.3)


def test_close_segments_get_the_direction_between_closest_points():
    # segment end near the middle of another: vertex-edge proximity through clamped parameters
    x0 = np.array([[0.0, 0.0, 0.3 * DELTA], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    c, nodes, mode, t, sign = _detect(x0, x0, [[0, 1]], [[2, 3]], "ee")
    assert c == 1 and mode[0] == EE_DIRECTION
    n, w = _geometry(x0, x0, nodes, mode, t, sign)
    np.testing.assert_allclose(n[0], [0.0, 0.0, 1.0], atol=1e-12)
    assert _constraint(x0, nodes, n, w)[0] == pytest.approx(0.3 * DELTA)


def test_self_queries_skip_incident_faces_and_shared_edges():
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    c, *_ = _detect(x, x, [0, 1, 2, 3], [[0, 1, 2], [1, 3, 2]], "vf", flag=1)
    assert c == 0
    edges = [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    c, *_ = _detect(x, x, edges, edges, "ee", flag=1)
    assert c == 0


def test_overflow_is_counted_beyond_the_capacity():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0.05, 0.4, 20), rng.uniform(0.05, 0.4, 20), np.full(20, 0.5 * DELTA)])
    x = np.vstack([TRI, pts])
    c, nodes, *_ = _detect(x, x, list(range(3, 23)), [[0, 1, 2]], "vf", capacity=5)
    assert c == 20 and len(nodes) == 5


@pytest.mark.parametrize("end_gap, found", [(0.3, False), (0.1, True)])
def test_keeping_start_gaps_a_vertex_inside_the_thickness_is_a_contact_only_where_it_comes_closer(end_gap, found):
    # The collision stage's second try (keep_start_gaps): a vertex that starts 0.2 thickness above a face is a
    # contact only where it ends closer than that (by more than START_SLACK), and then its target is its start gap;
    # the first try takes any vertex within the thickness and targets the thickness.
    tri = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    x0 = np.vstack([[0.0, 0.0, 0.2 * DELTA], tri])
    x1 = np.vstack([[0.0, 0.0, end_gap * DELTA], tri])
    count, nodes, mode, t, sign = _detect(x0, x1, [0], [[1, 2, 3]], "vf", keep_start_gaps=1)
    assert (count == 1) == found
    assert _detect(x0, x1, [0], [[1, 2, 3]], "vf")[0] == 1  # the first try's proximity contact
    if found:
        _, _, target = _geometry(x0, x1, nodes, mode, t, sign, keep_start_gaps=1, targets=True)
        np.testing.assert_allclose(target, [0.2 * DELTA], rtol=1e-12)
        _, _, target = _geometry(x0, x1, nodes, mode, t, sign, targets=True)
        np.testing.assert_allclose(target, [DELTA], rtol=1e-12)


def test_rows_appended_in_any_order_come_out_in_the_order_of_their_keys(device):
    """detection.RowSort and kernels/geometry.py world_starts, as detection, the pair search and the device
    projection use them: keys of three worlds (the middle one without rows, a tie among them) in a shuffled order,
    as CUDA's atomic appends leave them, are sorted stably (a tie keeps its slots' order), and each world's first
    row is found."""
    rng = np.random.default_rng(3)
    span = 1000
    keys = np.concatenate([rng.integers(0, span, 40), 2 * span + rng.integers(0, span, 25)])
    keys[7] = keys[3]
    rng.shuffle(keys)
    n = len(keys)
    rows = RowSort(n, 3 * span, device)
    rows.keys.assign(np.concatenate([keys, np.zeros(n, dtype=np.int64)]))
    rows.values.assign(np.arange(2 * n, dtype=np.int32))
    rows.sort(n)
    np.testing.assert_array_equal(rows.order.numpy(), np.argsort(keys, kind="stable"))
    start = wp.zeros(4, dtype=wp.int32, device=device)
    wp.launch(world_starts, 4, device=device,
              inputs=[rows.keys, wp.array([n], dtype=wp.int32, device=device), span], outputs=[start])
    assert start.numpy().tolist() == [0, 40, 40, 65]
    with pytest.raises(ValueError, match="sort keys of the rows .* do not fit in int64"):
        RowSort(4, 2**63, device)


@wp.kernel
def _filter_and_tests(x0: wp.array(dtype=wp.vec3d), x1: wp.array(dtype=wp.vec3d), vertex_face: int,
                      thickness: wp.float64, keep_start_gaps: int, out: wp.array2d(dtype=wp.int32)):
    # pair i: nodes 4i .. 4i + 3 (a vertex and a triangle, or two edges); out: [stay_apart, the full test's hit]
    i = wp.tid()
    a, b, c, d = 4 * i, 4 * i + 1, 4 * i + 2, 4 * i + 3
    apart = kc.stay_apart(vertex_face != 0, x0[a], x0[b], x0[c], x0[d], x1[a], x1[b], x1[c], x1[d], thickness)
    if vertex_face != 0:
        hit, _mode, _t, _sign, _rank = kc.vertex_face_test(x0[a], x0[b], x0[c], x0[d], x1[a], x1[b], x1[c], x1[d],
                                                           x1[a], x1[b], x1[c], x1[d], thickness, keep_start_gaps)
    else:
        hit, _mode, _t, _sign, _rank = kc.edge_edge_test(x0[a], x0[b], x0[c], x0[d], x1[a], x1[b], x1[c], x1[d],
                                                         x1[a], x1[b], x1[c], x1[d], thickness, keep_start_gaps)
    out[i, 0] = wp.where(apart, 1, 0)
    out[i, 1] = wp.where(hit, 1, 0)


def _near_pairs(rng, count, vertex_face, scale):
    """``count`` random pairs (a vertex and a triangle, or two edges) of primitives of size ``scale`` that start
    and end within a few thicknesses of each other, or cross, or pass: (x0, x1), 4 nodes a pair."""
    corners = rng.uniform(-1.0, 1.0, (count, 3, 3)) * scale
    weights = rng.dirichlet(np.ones(3), count) if vertex_face else None
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = DELTA * rng.uniform(-4.0, 4.0, (count, 1)) * normal + DELTA * rng.normal(0.0, 2.0, (count, 3))
    if vertex_face:
        # a third straight over the centroid, where the filter's direction is the face's normal: its bound is
        # tightest there
        centred = rng.uniform(size=count) < 1.0 / 3.0
        weights[centred] = 1.0 / 3.0
        offset[centred] = DELTA * rng.uniform(-2.0, 2.0, (int(centred.sum()), 1)) * normal[centred]
        point = np.einsum("kc,kcd->kd", weights, corners) + offset
        x0 = np.concatenate([point[:, None], corners], axis=1)
    else:  # the second edge crosses near a point of the first's plane
        along = corners[:, 0] + rng.uniform(-0.2, 1.2, (count, 1)) * (corners[:, 1] - corners[:, 0]) + offset
        half = rng.normal(0.0, 1.0, (count, 3)) * scale
        x0 = np.stack([corners[:, 0], corners[:, 1], along - half, along + half], axis=1)
    motion = rng.normal(0.0, 1.0, (count, 4, 3)) * DELTA * rng.choice([0.0, 0.1, 1.0, 10.0], (count, 1, 1))
    return x0.reshape(-1, 3), (x0 + motion).reshape(-1, 3)


@pytest.mark.parametrize("vertex_face", [True, False], ids=["vertex-face", "edge-edge"])
@pytest.mark.parametrize("keep_start_gaps", [0, 1])
def test_the_filter_in_front_of_the_tests_passes_every_pair_they_report(vertex_face, keep_start_gaps):
    # kernels/collision.py stay_apart skips a pair the query meets without testing it: only sound if no pair it
    # skips is one vertex_face_test or edge_edge_test reports (a crossing or a proximity contact). 60000 random
    # pairs at three sizes of primitive, all within a few thicknesses of each other at the start, moving by a tenth
    # of a thickness to ten thicknesses over the step.
    rng = np.random.default_rng(7 + keep_start_gaps + 2 * vertex_face)
    apart = hits = 0
    for scale in (2.0 * DELTA, 0.01, 1.0):
        x0, x1 = _near_pairs(rng, 20000, vertex_face, scale)
        out = wp.zeros((20000, 2), dtype=wp.int32)
        wp.launch(_filter_and_tests, 20000, inputs=[wp.array(x0, dtype=wp.vec3d), wp.array(x1, dtype=wp.vec3d),
                                                    int(vertex_face), DELTA, keep_start_gaps], outputs=[out])
        o = out.numpy()
        wrong = np.flatnonzero(o[:, 0] & o[:, 1])
        assert wrong.size == 0, f"scale {scale}: {wrong.size} pairs skipped that the test reports, e.g. {wrong[:3]}"
        apart += int(o[:, 0].sum())
        hits += int(o[:, 1].sum())
    # both kinds are common among these pairs, so a filter that skipped too much would have been caught
    assert apart > 6000 and hits > 6000, (apart, hits)

"""NumPy reference of SPEC.md §1.2-1.3, written independently of the Warp kernels (test oracle only)."""

import numpy as np

N = 30


def grid_sample_align_corners(data: np.ndarray, x: float, y: float) -> np.ndarray:
    """Bilinear sample of data (C, H, W) at pixel coordinates x (along W), y (along H), border padding."""
    C, H, W = data.shape
    x = min(max(x, 0.0), W - 1.0)
    y = min(max(y, 0.0), H - 1.0)
    x0 = min(int(np.floor(x)), W - 2) if W > 1 else 0
    y0 = min(int(np.floor(y)), H - 2) if H > 1 else 0
    fx, fy = x - x0, y - y0
    top = (1 - fx) * data[:, y0, x0] + fx * data[:, y0, min(x0 + 1, W - 1)]
    bot = (1 - fx) * data[:, min(y0 + 1, H - 1), x0] + fx * data[:, min(y0 + 1, H - 1), min(x0 + 1, W - 1)]
    return (1 - fy) * top + fy * bot


def stretching_samples(table: np.ndarray) -> np.ndarray:
    """ARCSim's 30^3 x 4 stiffness samples from a raw 6x4 stretching table (before thicken)."""
    data = np.zeros((4, 2, 5))
    data[:, 0, :] = table[0][:, None]
    for j in range(5):
        data[:, 1, j] = table[j + 1]
    out = np.zeros((N, N, N, 4))
    for i in range(N):
        for j in range(N):
            for k in range(N):
                c00, c11, c01 = 0.5 + 2 * i / N, 0.5 + 2 * j / N, 2 * k / N
                w = 0.5 * (c00 + c11 + np.sqrt(4 * c01**2 + (c00 - c11) ** 2))
                if k == 0:
                    v = (1.0, 0.0) if i >= j else (0.0, 1.0)
                else:
                    v = (w - c11, c01)
                angle = abs(np.arctan2(v[1], v[0]) / np.pi) * 8
                strain = (np.sqrt(w) - 1) * 6
                out[i, j, k] = np.maximum(2 * grid_sample_align_corners(data, angle, strain), 0.0)
    return out


def trilinear(samples: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    idx = []
    for v in (a, b, c):
        v = min(max(v, 0.0), N - 1.0)
        i0 = min(int(np.floor(v)), N - 2)
        idx.append((i0, v - i0))
    (i, fi), (j, fj), (k, fk) = idx
    out = np.zeros(4)
    for di, wi in ((0, 1 - fi), (1, fi)):
        for dj, wj in ((0, 1 - fj), (1, fj)):
            for dk, wk in ((0, 1 - fk), (1, fk)):
                out += wi * wj * wk * samples[i + di, j + dj, k + dk]
    return out


def stretching_force(x: np.ndarray, uv: np.ndarray, samples: np.ndarray, thicken: float) -> np.ndarray:
    """Forces (3, 3) on the nodes of one face, SPEC §1.2."""
    Dm = np.column_stack([uv[1] - uv[0], uv[2] - uv[0]])
    A = 0.5 * np.linalg.det(Dm)
    F = np.column_stack([x[1] - x[0], x[2] - x[0]]) @ np.linalg.inv(Dm)
    G = 0.5 * (F.T @ F - np.eye(2))
    k = thicken * trilinear(samples, (G[0, 0] + 0.25) * N, (G[1, 1] + 0.25) * N, abs(G[0, 1]) * N)
    d = np.linalg.inv(Dm)  # [[d0, d1], [d2, d3]]
    Du = np.hstack([(-d[0, 0] - d[1, 0]) * np.eye(3), d[0, 0] * np.eye(3), d[1, 0] * np.eye(3)])
    Dv = np.hstack([(-d[0, 1] - d[1, 1]) * np.eye(3), d[0, 1] * np.eye(3), d[1, 1] * np.eye(3)])
    xu, xv = F[:, 0], F[:, 1]
    fuu, fvv, fuv = Du.T @ xu, Dv.T @ xv, Du.T @ xv + Dv.T @ xu
    f = -A * (k[0] * G[0, 0] * fuu + k[2] * G[1, 1] * fvv + k[1] * (G[0, 0] * fvv + G[1, 1] * fuu)
              + k[3] * G[0, 1] * fuv)
    return f.reshape(3, 3)


def dihedral(x0, x1, x2, x3):
    n0 = np.cross(x1 - x0, x2 - x0)
    n0 /= np.linalg.norm(n0)
    n1 = np.cross(x3 - x0, x1 - x0)
    n1 /= np.linalg.norm(n1)
    e = (x0 - x1) / np.linalg.norm(x0 - x1)
    return np.arctan2(e @ np.cross(n0, n1), n0 @ n1), n0, n1


def bending_force(x: np.ndarray, length: float, area_sum: float, directions, table: np.ndarray, thicken: float):
    """Forces (4, 3) on the hinge nodes (x0, x1 edge; x2, x3 opposite), SPEC §1.3, rest angle 0."""
    x0, x1, x2, x3 = x
    theta, n0, n1 = dihedral(x0, x1, x2, x3)
    e = x1 - x0
    t0 = e @ (x2 - x0) / (e @ e)
    t1 = e @ (x3 - x0) / (e @ e)
    h0 = max(np.linalg.norm(x2 - x0 - e * t0), 1e-3 * np.linalg.norm(e))
    h1 = max(np.linalg.norm(x3 - x0 - e * t1), 1e-3 * np.linalg.norm(e))
    g2, g3 = n0 / h0, n1 / h1
    grad = np.array([(t0 - 1) * g2 + (t1 - 1) * g3, -t0 * g2 - t1 * g3, g2, g3])
    curv = min(max(0.1 * theta * length / area_sum, 0.0), 4.0)
    ke = min(max(grid_sample_align_corners(table[None], curv, a)[0], 0.0) for a in directions) * thicken
    kappa = -ke * length**2 / (4 * area_sum)
    return kappa * theta * grad

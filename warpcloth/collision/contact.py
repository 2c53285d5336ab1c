"""The contacts' nodes and geometry at their time of impact, shared by the projection backends and the fail-safe."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpcloth.collision.detection import ContactDetector, Contacts
from warpcloth.errors import CollisionError
from warpcloth.kernels.contact import contact_kernels
from warpcloth.model import Model


def gather_nodes(model: Model, cloth_x: wp.array, obstacle_x: wp.array, recording: bool,
                 out: wp.array | None = None) -> wp.array:
    """Every node's position, cloth particles then obstacle vertices: a new taped array, or untaped into ``out``."""
    n = model.particle_count
    taped = out is None
    if taped:
        out = wp.empty(n + obstacle_x.shape[0], dtype=model.types.vec3, device=model.device, requires_grad=recording)
    wp.launch(contact_kernels(model.scalar).gather_nodes, out.shape[0], device=model.device,
              inputs=[cloth_x, obstacle_x, n], outputs=[out], record_tape=taped)
    return out


def contact_geometry(model: Model, detector: ContactDetector, start: wp.array, end: wp.array, contacts: Contacts,
                     recording: bool, step: int) -> tuple[wp.array, wp.array, wp.array]:
    """Normals, weights and target gaps of host ``contacts`` at their time of impact (taped; each world's target as
    ``detector.world_mode`` says); raises CollisionError naming a contact whose normal is degenerate."""
    normal, weight, target = geometry_arrays(model, len(contacts), recording)
    dev = model.device
    wp.launch(contact_kernels(model.scalar).geometry, len(contacts), device=dev,
              inputs=[start, end, wp.array(contacts.nodes, dtype=wp.int32, device=dev),
                      wp.array(contacts.mode, dtype=wp.int32, device=dev),
                      wp.array(contacts.t, dtype=wp.float64, device=dev),
                      wp.array(contacts.sign, dtype=wp.float64, device=dev), model.scalar(model.collision.thickness),
                      detector.world_mode, detector.node_world],
              outputs=[normal, weight, target])
    ok = np.all(np.isfinite(normal.numpy()), axis=1) & np.all(np.isfinite(weight.numpy()), axis=1)
    if not ok.all():
        raise degenerate_error(step, contacts.nodes[int(np.flatnonzero(~ok)[0])], detector)
    return normal, weight, target


def geometry_arrays(model: Model, count: int, recording: bool) -> tuple[wp.array, wp.array, wp.array]:
    dev = model.device
    return (wp.empty(count, dtype=model.types.vec3, device=dev, requires_grad=recording),
            wp.empty(count, dtype=model.types.vec4, device=dev, requires_grad=recording),
            wp.empty(count, dtype=model.scalar, device=dev, requires_grad=recording))


def degenerate_error(step: int, nodes: np.ndarray, detector: ContactDetector) -> CollisionError:
    world = int(detector.node_world_host[nodes[0]])
    return CollisionError(f"step {step}: a contact between nodes {nodes.tolist()} has a degenerate normal; a triangle "
                          "or edge of the cloth or of an obstacle collapsed", worlds=[world])

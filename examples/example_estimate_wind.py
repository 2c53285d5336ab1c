"""Gradient descent on Warp's tape: recover the wind that blew a cloth from its observed motion.

A target trajectory is simulated with a known wind; starting from a wrong guess, the wind velocity is fitted by
differentiating the squared distance between trajectories through the whole rollout. Only the wind's component
along the cloth's normals acts on it (ARCSim's model has no tangential drag by default), so only the speed along x
(the cloth faces +x) is fitted: the other components are not identifiable from this motion.

The rollout, its loss and its backward pass are recorded once as a graph (``wc.CapturedRollout``) and replayed at
every iteration: the wind is changed in place between replays, and each replay leaves the loss's gradient in
``model.wind_velocity.grad``.

At the end the cloth blown by the fitted wind is drawn against the target (translucent).

    python examples/example_estimate_wind.py --iters 30 --preview wind.gif
"""

import argparse

import numpy as np
import warp as wp

import warpcloth as wc
from warpcloth.kernels.losses import loss_kernels
from warpcloth.preview import write_preview
from warpcloth.tasks.scenes import GRID_TO_YZ


class Example:
    def __init__(self, *, steps: int = 20, true_speed: float = 4.0, guess: float = 1.0, device=None):
        builder = wc.ModelBuilder()
        builder.add_cloth_grid((8, 8), (0.5, 0.5), material=wc.preset("tango-red-jet-set", thicken=2),
                               rot=GRID_TO_YZ, pos=(0.0, -0.25, -0.25))
        builder.add_handle(8 * 9)
        builder.add_handle(8 * 9 + 8)
        builder.set_wind((true_speed, 0.0, 0.0))
        self.model = builder.finalize(device, requires_grad=True)
        self.sim = wc.Simulator(self.model, 0.02)
        self.steps = steps
        self.squared_distance = loss_kernels(self.model.scalar).squared_distance  # loss += scale |x - target|^2
        self.targets = [s.particle_x for s in wc.rollout(self.sim, self.model.state(), steps=steps)]
        self.model.wind_velocity.assign([(guess, 0.0, 0.0)])
        self.captured = wc.CapturedRollout(self.sim, self.model.state(), steps=steps, loss=self.loss_of)
        # Adam on the wind speed along x (the component normal to the cloth): the loss's scale is unknown upfront
        self.learning_rate = 0.3
        self.moments = [0.0, 0.0]
        self.iteration = 0

    def loss_of(self, trajectory) -> wp.array:
        """Mean squared distance to the target trajectory (kernels launched on the trajectory: recorded too)."""
        loss = wp.zeros(1, dtype=float, requires_grad=True)
        scale = 1.0 / (self.steps * self.model.particle_count)
        for state, target in zip(trajectory[1:], self.targets[1:]):
            wp.launch(self.squared_distance, self.model.particle_count,
                      inputs=[state.particle_x, target, scale], outputs=[loss])
        return loss

    def loss_and_grad(self) -> float:
        self.captured.run()  # forward, loss and backward: the gradient is in model.wind_velocity.grad
        return float(self.captured.loss.numpy()[0])

    def step(self) -> float:
        loss = self.loss_and_grad()
        g = float(self.model.wind_velocity.grad.numpy()[0, 0])
        self.iteration += 1
        m = self.moments[0] = 0.5 * self.moments[0] + 0.5 * g
        v = self.moments[1] = 0.999 * self.moments[1] + 0.001 * g * g
        step = self.learning_rate * (m / (1 - 0.5**self.iteration)) / (np.sqrt(v / (1 - 0.999**self.iteration)) + 1e-12)
        speed = float(self.model.wind_velocity.numpy()[0, 0]) - step
        self.model.wind_velocity.assign([(speed, 0.0, 0.0)])
        return loss

    def save_preview(self, path: str) -> None:
        """Draw the cloth in the current wind against the target motion (.gif, .png or, with ffmpeg, .mp4)."""
        frames = [s.particle_x.numpy() for s in wc.rollout(self.sim, self.model.state(), steps=self.steps)]
        tris = self.model.tri_indices.numpy()
        target = np.stack([x.numpy() for x in self.targets])
        write_preview(path, triangles=tris, frames=frames, fps=1.0 / self.sim.dt, obstacles=[("target", target, tris)],
                      title="fitted wind")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--iters", type=int, default=30)
    parser.add_argument("--preview", default="example_estimate_wind.gif", help=".gif, .png or .mp4 (ffmpeg)")
    args = parser.parse_args()
    example = Example(device=args.device)
    for it in range(args.iters):
        loss = example.step()
        print(f"iter {it:3d}  loss {loss:.3e} m^2  wind {example.model.wind_velocity.numpy()[0].round(3)}")
    example.save_preview(args.preview)
    print(f"wrote {args.preview}")

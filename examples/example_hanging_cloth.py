"""A cloth hanging from two corners in the wind, written to a time-sampled USD file and drawn as an animated GIF.

The scene is the seed's material-estimation setup (``warpcloth.tasks.scenes.hanging_cloth``): a 1 m gray-interlock
sheet, soft handles (1e3 N/m) on its top corners, a 5 m/s wind along +x.

    python examples/example_hanging_cloth.py --num-frames 100 --usd-path hanging.usda --preview-path hanging.gif
"""

import argparse

import warp as wp

import warpcloth as wc
from warpcloth.tasks import scenes


class Example:
    def __init__(self, *, res: int = 16, device=None, usd_path: str | None = None, preview_path: str | None = None):
        self.model = scenes.hanging_cloth(wc.preset("gray-interlock", thicken=2), res=res, device=device,
                                          requires_grad=False)
        self.sim = wc.Simulator(self.model, 1.0 / 50.0)
        self.state = self.model.state()
        self.next_state = self.model.empty_state()
        self.frames = [self.state.particle_x.numpy().copy()]  # a copy: the states' buffers are reused
        self.usd_path = usd_path
        self.preview_path = preview_path

    def step(self):
        self.sim.step(self.state, self.next_state)
        self.state, self.next_state = self.next_state, self.state

    def render(self):
        self.frames.append(self.state.particle_x.numpy().copy())

    def save(self):
        if self.usd_path:
            from warpcloth.usd import write_usd

            write_usd(self.usd_path, triangles=self.model.triangles_np, frames=self.frames, fps=1.0 / self.sim.dt)
        if self.preview_path:  # a picture without a USD viewer (.gif, .png or, with ffmpeg, .mp4)
            from warpcloth.preview import write_preview

            write_preview(self.preview_path, triangles=self.model.triangles_np, frames=self.frames,
                          fps=1.0 / self.sim.dt, title="hanging cloth")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0")
    parser.add_argument("--num-frames", type=int, default=100)
    parser.add_argument("--usd-path", default="example_hanging_cloth.usda")
    parser.add_argument("--preview-path", default="example_hanging_cloth.gif", help=".gif, .png or .mp4 (ffmpeg)")
    args = parser.parse_args()
    with wp.ScopedDevice(args.device):
        example = Example(device=args.device, usd_path=args.usd_path, preview_path=args.preview_path)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        example.save()
    print(f"{args.num_frames} steps, {example.sim.stats['cg_iterations']} CG iterations; wrote {args.usd_path} "
          f"and {args.preview_path}")

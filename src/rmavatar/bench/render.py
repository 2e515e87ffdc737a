"""``rmavatar bench render RUN``: frames per second of a trained avatar, and where a frame's time goes.

A frame is what animate and the viewer do per frame: pose the body for one pose, put the Gaussians on
the mesh and rectify them, evaluate their colours for the camera and rasterize. Two paths are timed, each
as the median over ``--frames`` frames after a warm-up, synchronised around every timed block on CUDA:

- ``frame``: ``TrainedAvatar.pose`` (body + mesh embedding + rectifier, one replayed CUDA graph on a GPU)
  then colours + rasterizer: what animate does;
- ``stages``: the same work eagerly, stage by stage (body forward, mesh embedding, rectifier,
  colours + rasterizer), to show the split.

The poses cycle through the run's training poses (or ``--motion``), seen by a front camera framing the
body, at ``--size`` x ``--size``.
"""

from __future__ import annotations

import argparse


def _poses(trained, motion: str | None):
    from rmavatar.animate.motion import recenter_motion
    from rmavatar.body import PoseSequence
    from rmavatar.body.motion import load_motion, motion_to_sequence
    from rmavatar.data import load_dataset

    if motion:
        seq = motion_to_sequence(load_motion(motion))
    elif trained.training_poses is not None:
        seq = trained.training_poses
    else:
        p = load_dataset(trained.data_spec).params(trained.training_split)
        seq = PoseSequence.from_params(p)
    return recenter_motion(seq, trained.root_rest())


def measure(trained, seq, size: int, frames: int, warmup: int, graph: bool = True) -> dict:
    """Median seconds per frame of both paths (module docstring) and the stages' split."""
    import torch

    from rmavatar.animate.camera import intrinsics, preset_viewmat
    from rmavatar.animate.jobs import VideoOptions, frame_the_body
    from rmavatar.bench.timing import Clock
    from rmavatar.render import rasterize

    dev = trained.device
    sync = torch.cuda.synchronize if dev.type == "cuda" else None
    center, distance = frame_the_body(trained.vertices(seq.select(slice(0, min(len(seq), 16)))), VideoOptions())
    view = preset_viewmat("front", center, distance).to(dev)
    K = intrinsics(size, size, VideoOptions().fov_deg).to(dev)
    bg = torch.ones(3, device=dev)
    seq = seq.to(dev)
    trained.cuda_graphs = graph

    def draw(gs):
        rasterize(gs.means, gs.quats, gs.scales, gs.opacities, gs.colors(view), view, K, size, size, background=bg)

    frame, posing, raster = Clock(sync), Clock(sync), Clock(sync)
    with torch.no_grad():
        for k in range(warmup + frames):
            timed = k >= warmup
            with _maybe(frame, timed):
                with _maybe(posing, timed):
                    gs = trained.pose(seq, k % len(seq), keep=False)
                with _maybe(raster, timed):
                    draw(gs)
        stages = {name: Clock(sync) for name in ("body_forward", "mesh_embedding", "rectifier", "colors_rasterize")}
        av = trained.avatar
        for k in range(warmup + frames):
            timed = k >= warmup
            one = seq.select(slice(k % len(seq), k % len(seq) + 1))
            with _maybe(stages["body_forward"], timed):
                vertices = trained.vertices(one)[0]
            with _maybe(stages["mesh_embedding"], timed):
                av.posed(vertices)
            with _maybe(stages["rectifier"], timed):  # the whole forward minus the embedding timed above
                gs = trained.gaussians(vertices, one.body_pose[0], one.hand(0))
            with _maybe(stages["colors_rasterize"], timed):
                draw(gs)
    split = {name: c.result()["wall_s"] for name, c in stages.items()}
    split["rectifier"] = max(0.0, split["rectifier"] - split["mesh_embedding"])
    f = frame.result()["wall_s"]
    poser = trained.posing_graph
    return {
        "size": size, "frames": frames, "gaussians": trained.avatar.num_gaussians,
        "frame_s": f, "fps": 1.0 / f, "posing_s": posing.result()["wall_s"], "raster_s": raster.result()["wall_s"],
        "graph": {"used": bool(poser is not None and poser.captures > 0 and poser.enabled),
                  "captures": 0 if poser is None else poser.captures,
                  "off_reason": (poser.off_reason if poser is not None and poser.off_reason else
                                 None if trained.device.type == "cuda" else "not a CUDA device")},
        "stages_s": split, "stages_frame_s": sum(split.values()),
    }


class _maybe:
    """``clock`` around a block when ``timed``, else nothing."""

    def __init__(self, clock, timed: bool):
        self.clock, self.timed = clock, timed

    def __enter__(self):
        if self.timed:
            self.clock.__enter__()

    def __exit__(self, *exc):
        if self.timed:
            self.clock.__exit__(*exc)
        return False


def run(args: argparse.Namespace) -> int:
    from rmavatar.avatar import load_trained
    from rmavatar.bench.step import device_info
    from rmavatar.utils import resolve_device

    device = resolve_device(args.device)
    trained = load_trained(args.run, device=device)
    res = {**device_info(device), **measure(trained, _poses(trained, args.motion), args.size, args.frames,
                                            args.warmup, graph=not args.no_cuda_graphs)}
    gpu = f" ({res['gpu']})" if "gpu" in res else ""
    g = res["graph"]
    how = "one CUDA graph" if g["used"] else f"eager ({g['off_reason']})"
    print(f"rendering {res['gaussians']} Gaussians at {args.size}x{args.size} on {res['device']}{gpu}:")
    print(f"  frame {1e3 * res['frame_s']:.2f} ms = {res['fps']:.0f} FPS: posing + rectifier "
          f"{1e3 * res['posing_s']:.2f} ms "
          f"({how}), colours + rasterizing {1e3 * res['raster_s']:.2f} ms")
    print("  eager, stage by stage: " + ", ".join(f"{k} {1e3 * v:.2f} ms" for k, v in res["stages_s"].items()))
    if args.json:
        from rmavatar.utils.outputs import write_json

        write_json(args.json, res, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0

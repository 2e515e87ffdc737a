"""``rmavatar bench avatar``: the avatar's forward + backward (posing + rectifier), the part of a training
step it owns, for the rectifier in float32 and bfloat16 and without a rectifier.

    rmavatar bench avatar --gaussians 25000 --repeats 20 [--threads 2] [--body anny] [--json FILE]

Prints one JSON object (and writes it to ``--json FILE``): median / min wall seconds and median process
CPU seconds per step, for the default rectifier design (``model.rectifier``) in float32 and bfloat16
and without a rectifier, each avatar built by its config on the body (as training builds it), posed in
a random pose. The machine's other load shows in the wall times; CPU seconds (summed over threads) are
steadier on a shared machine.
"""

from __future__ import annotations

import json
import statistics

import torch

from rmavatar.bench.timing import timed


def time_avatar(avatar, vertices: torch.Tensor, body_pose: torch.Tensor, repeats: int = 20, warmup: int = 3) -> dict:
    """Seconds per forward + backward of ``avatar(vertices, body_pose)`` with a loss over all outputs."""

    def step():
        g, extras = avatar.forward_with_extras(vertices, body_pose)
        loss = g.means.sum() + g.quats.sum() + g.scales.sum() + g.opacities.sum() + g.sh.sum()
        if extras.offsets is not None:
            loss = loss + sum(o.square().sum() for o in extras.offsets)
        loss.backward()
        avatar.zero_grad(set_to_none=True)

    clock = timed(step, repeats, warmup=warmup)
    return {"wall_median_s": statistics.median(clock.wall), "wall_min_s": min(clock.wall),
            "cpu_median_s": statistics.median(clock.cpu)}


def run(opts) -> int:
    """``opts``: the options of ``rmavatar bench avatar`` (gaussians, repeats, threads, body, json, overwrite)."""
    from rmavatar.avatar import AvatarConfig
    from rmavatar.avatar.rectifier import cpu_multiplies_bf16
    from rmavatar.body import load_body_model

    if opts.threads:
        torch.set_num_threads(opts.threads)
    body = load_body_model(opts.body)
    torch.manual_seed(0)
    pose = torch.randn(69) * 0.3
    with torch.no_grad():
        verts = body(None, torch.zeros(1, 3), pose[None], torch.zeros(1, 3)).vertices[0]
    result = {"gaussians": opts.gaussians, "threads": torch.get_num_threads(), "body": body.spec,
              "faces": int(body.faces.shape[0]), "rectifier": AvatarConfig().rectifier,
              "cpu_multiplies_bf16": cpu_multiplies_bf16()}  # where "auto" (the default) takes bfloat16
    for name, cfg in (
        ("no_rectifier", AvatarConfig(rectifier=False)),
        ("rectifier_float32", AvatarConfig(rectifier_precision="float32")),
        ("rectifier_bfloat16", AvatarConfig(rectifier_precision="bfloat16")),
    ):
        cfg.placement, cfg.num_gaussians = "area", opts.gaussians
        avatar = cfg.build(body)
        avatar.active_sh_degree.fill_(cfg.sh_degree)
        result[name] = time_avatar(avatar, verts, pose, opts.repeats)
    print(json.dumps(result, indent=2))
    if opts.json:
        from rmavatar.utils.outputs import write_json

        write_json(opts.json, result, overwrite=opts.overwrite)
    return 0

"""``rmavatar train DATA --out RUN``: fit an avatar to a dataset's training frames."""

from __future__ import annotations

import argparse

from rmavatar.utils import UserError

EPILOG = """examples:
  rmavatar train data/subject --out runs/subject --size 256 --iters 3000
  rmavatar train data/subject --out runs/subject --resume          # continue after a stop or a crash
  rmavatar train peoplesnapshot:data/male-3-casual --out runs/m3c --body smpl:models/smpl --size 540
  rmavatar train data/subject --out runs/norect --no-rectifier       # the paper's "w/o GauRec" ablation
  rmavatar train data/subject --out runs/again --config runs/subject/config.yaml
  rmavatar train data/captured --out runs/cap --no-refine-poses      # keep the tracker's poses as they are

Every run folder gets config.yaml (edit it and pass it back with --config), checkpoints/last.pt
(written every log.checkpoint_every iterations, at the end and on Ctrl-C), previews/*.png (render |
target) and tb/ (TensorBoard: tensorboard --logdir RUN/tb); runs that refine their poses also get
poses.npz and pose_pass/ (the first pass, a run of its own), and subjects from rmavatar synth
pose_error.json. Command-line options override the config file."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    parser.add_argument("data", metavar="DATA",
                        help="dataset: a folder (native, PeopleSnapshot or ZJU-MoCap layout, detected) or KIND:PATH")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder to create (or continue with --resume)")
    parser.add_argument("--body", metavar="SPEC",
                        help="body model: anny, anny:PRESET or smpl:PATH (default: the dataset's preset and gender)")
    parser.add_argument("--iters", type=int, metavar="N", help="training iterations (default 50000, the paper's)")
    parser.add_argument("--size", type=int, metavar="S",
                        help="resample frames so the longer side is S pixels (default: native resolution)")
    parser.add_argument("--config", metavar="FILE", help="YAML config (e.g. a previous RUN/config.yaml)")
    parser.add_argument("--resume", action="store_true",
                        help="continue RUN from checkpoints/last.pt with its saved config (--iters may extend it)")
    parser.add_argument("--no-rectifier", action="store_true", help="ablation: no Gaussian rectification MLP")
    parser.add_argument("--no-offset-loss", action="store_true", help="ablation: offset regulariser weight 0")
    parser.add_argument("--no-scaling-loss", action="store_true", help="ablation: scaling regulariser weight 0")
    parser.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                        help="learn per-frame corrections of the training poses: smoothed over +-2 frames, "
                             "then fitted to every training image near the end of a first pass of 10%% of "
                             "the iterations (RUN/pose_pass); the avatar is then trained afresh on them for the "
                             "full iterations and fits them again at 25%%, 60%% and 85%% of it (five times, "
                             "at 20%%, 40%%, 60%%, 80%% and 95%%, from 60 iterations per training frame; poses.smooth, "
                             "poses.first_pass, poses.fits, poses.held_fits; docs/train.md). "
                             "Default: on when the dataset's poses are "
                             "estimated, as rmavatar capture's are; off otherwise")
    parser.add_argument("--hand-pose", action=argparse.BooleanOptionalAction, default=None,
                        help="pose the fingers with the dataset's finger poses (hand_pose in smpl.npz, from "
                             "rmavatar capture or synth --hand-motion) where it has them; --no-hand-pose: "
                             "relaxed hands (data.hand_pose; default on; docs/hands.md)")
    parser.add_argument("--bg", choices=("white", "black", "random"), help="background colour (default white)")
    parser.add_argument("--seed", type=int, metavar="N", help="random seed (default 0)")
    parser.add_argument("--checkpoint-every", type=int, metavar="K", help="checkpoint interval in iterations")
    parser.add_argument("--threads", type=int, metavar="T", help="torch CPU threads (default: torch's choice)")


def config_from_args(args: argparse.Namespace):
    """The TrainConfig for a fresh run: --config file (or defaults), then command-line overrides."""
    from rmavatar.train.config import TrainConfig, apply_overrides, load_config

    cfg = load_config(args.config) if args.config else TrainConfig()
    return apply_overrides(cfg, {"data.path": args.data, **_overrides(args)}, where="the command line").validate()


def _overrides(args: argparse.Namespace) -> dict[str, object]:
    """The config settings (dotted keys) of every option the user actually gave."""
    out = {}
    plain = [("body", "model.body"), ("iters", "optim.iters"), ("size", "data.size"), ("bg", "background"),
             ("seed", "seed"), ("checkpoint_every", "log.checkpoint_every"), ("threads", "threads"),
             ("refine_poses", "poses.refine"), ("hand_pose", "data.hand_pose")]
    for attr, key in plain:
        value = getattr(args, attr, None)
        if value is not None:
            out[key] = value
    if getattr(args, "no_rectifier", False):
        out["model.rectifier"] = False
    if getattr(args, "no_offset_loss", False):
        out["loss.offset"] = 0.0
    if getattr(args, "no_scaling_loss", False):
        out["loss.scaling"] = 0.0
    return out


def run(args: argparse.Namespace) -> int:
    from rmavatar.train import train

    if args.threads is not None and args.threads < 1:  # the config's 0 ("torch's choice") is leaving it out here
        raise UserError(f"--threads must be >= 1 (leave it out for torch's choice), got {args.threads}")
    if args.resume:
        if args.config:
            raise UserError("--resume continues with the run's own config; do not pass --config")
        result = train(None, args.out, resume=True, data=args.data, overrides=_overrides(args))
    else:
        result = train(config_from_args(args), args.out)
    return 130 if result.interrupted else 0

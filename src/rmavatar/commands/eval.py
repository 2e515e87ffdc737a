"""``rmavatar eval``: PSNR / SSIM / LPIPS of a trained run on a dataset split, with the protocol stated."""

from __future__ import annotations

import argparse
from pathlib import Path

from rmavatar.utils import UserError
from rmavatar.utils.outputs import add_overwrite_argument, check_output_file, write_json

DESCRIPTION = """\
Render every frame of a dataset split with a trained avatar and score it against the ground truth:
PSNR (20 log10(1/RMSE) per image), SSIM (11x11 Gaussian window, sigma 1.5) and LPIPS (AlexNet v0.1,
inputs in [-1, 1]) over full images, per frame and averaged. The JSON holds the per-frame rows, the
means and the protocol (background, resolution, split, iteration, poses used). Side-by-side images
(render | ground truth | error heat map) go to --images. A run that refined its training poses is scored
on its own training split with the refined poses. --fit-poses first fits each evaluated frame's pose
to its image and mask with the avatar frozen (the protocol InstantAvatar and GART report PeopleSnapshot
with); the checkpoint is never changed.

examples:
  rmavatar eval runs/female-3 --json eval_test.json
  rmavatar eval runs/female-3 --split novel_pose --bg black --size 540 --json eval_np.json
  rmavatar eval runs/female-3 --data peoplesnapshot:data/female-3-casual --json e.json --no-images
  rmavatar eval runs/female-3 --fit-poses --json eval_test_fit.json        # 100 fitting steps per frame
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = DESCRIPTION
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("run", metavar="RUN", help="training run folder (holds checkpoints/last.pt)")
    parser.add_argument("--json", required=True, metavar="OUT", help="where to write the results (JSON)")
    parser.add_argument("--data", metavar="DATA", help="dataset to evaluate on (default: the run's own)")
    parser.add_argument("--split", default="test",
                        help="which frames: test (default), novel_pose, val, novel_view, train, or any split "
                             "the dataset has")
    parser.add_argument("--bg", default="white", choices=["white", "black"],
                        help="background behind render and ground truth (default: white, as InstantAvatar "
                             "and the SplattingAvatar family report on PeopleSnapshot)")
    parser.add_argument("--size", type=int, metavar="S",
                        help="longer image side in pixels (default: the size the run was trained at)")
    parser.add_argument("--images", metavar="DIR",
                        help="folder for side-by-side images (default: OUT without .json, plus _images)")
    parser.add_argument("--no-images", action="store_true", help="do not write comparison images")
    parser.add_argument("--frames", type=int, metavar="N", help="evaluate only the first N frames of the split")
    parser.add_argument("--fit-poses", type=int, nargs="?", const=100, default=None, metavar="STEPS",
                        help="fit every evaluated frame's pose (joint rotations and translation) to its image "
                             "and mask before scoring, STEPS Adam steps (default 100); off unless given")
    parser.add_argument("--fit-smooth", type=int, default=2, metavar="FRAMES",
                        help="with --fit-poses, first average each given pose with its neighbours within FRAMES "
                             "frames, per joint, weighted by closeness (default 2; 0 = fit from the poses as given)")
    parser.add_argument("--fit-batch", type=int, default=8, metavar="B",
                        help="frames fitted together with --fit-poses (default 8; lower it if memory runs out)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda or cuda:N")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite_argument(parser)


def default_images_dir(json_path: Path) -> Path:
    stem = json_path.name[: -len(".json")] if json_path.name.endswith(".json") else json_path.name
    return json_path.with_name(stem + "_images")


def run(args: argparse.Namespace) -> int:
    from rmavatar.evaluate.run import check_images_dir, evaluate_run

    out = Path(args.json)
    # Options that would have no effect are errors, not silently ignored.
    if args.no_images and args.images:
        raise UserError("--images and --no-images contradict each other: give one of them")
    if args.fit_poses is None:
        unused = [o for o, v, d in (("--fit-smooth", args.fit_smooth, 2), ("--fit-batch", args.fit_batch, 8)) if v != d]
        if unused:
            raise UserError(f"{' and '.join(unused)} only matter{'s' if len(unused) == 1 else ''} with --fit-poses: "
                            f"add --fit-poses or leave {'it' if len(unused) == 1 else 'them'} out")
    # Fail before the long part, not after it.
    check_output_file(args.json, option="--json", overwrite=args.overwrite)  # the string: 'e.json/' is refused
    if args.frames is not None and args.frames < 1:
        raise UserError(f"--frames must be >= 1, got {args.frames}")
    if args.size is not None and args.size < 32:
        raise UserError(f"--size must be at least 32 pixels (LPIPS needs 32x32), got {args.size}")
    images = None if args.no_images else (Path(args.images) if args.images else default_images_dir(out))
    if images is not None:
        # Compared as resolved paths: '--json out.json --images ./out.json/' names one path twice.
        if images.resolve() == out.resolve() or images.resolve() in out.resolve().parents:
            raise UserError(f"--images {images} would hold the --json file {out}: give them different paths")
        check_images_dir(images, args.overwrite)

    fit = None
    if args.fit_poses is not None:
        from rmavatar.evaluate.fit import PoseFitConfig

        fit = PoseFitConfig(steps=args.fit_poses, batch=args.fit_batch, smooth=args.fit_smooth).validate()
    result = evaluate_run(
        args.run, data=args.data, split=args.split, bg=args.bg, size=args.size, out_dir=images,
        device=args.device, max_frames=args.frames, progress=not args.quiet, overwrite=args.overwrite, fit=fit,
    )
    write_json(out, result, overwrite=args.overwrite)

    p = result["protocol"]
    m = result["mean"]
    psnr = "inf" if m["psnr"] is None else f"{m['psnr']:.2f}"
    print(f"{p['split']}: {p['frames']} frames at {p['resolution'][0]}x{p['resolution'][1]}, {p['background']} "
          f"background, iteration {p['iteration']}")
    print(f"PSNR {psnr} dB   SSIM {m['ssim']:.4f}   LPIPS {m['lpips']:.4f}")
    if "pose_error" in result:
        e = result["pose_error"]
        print(f"pose error vs the true poses (mean per-joint angle): dataset {e['given']['joint_angle_deg']:.2f} deg, "
              f"used {e['used']['joint_angle_deg']:.2f} deg ({p['poses']} poses)")
    print(f"wrote {out}" + (f" and images in {images}" if images is not None else ""))
    return 0

"""What a training run tells its user: the progress bar, TensorBoard, previews (:class:`Reporter`), and the
guard that skips and counts non-finite steps on the device (:func:`finite_flag`, :class:`NonFiniteGuard`).

A step's tensors are read (one host sync for all of them) only at a logging iteration; so are the
non-finite-step counters, which stop the run after ``log.max_bad_steps`` consecutive skipped steps.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from rmavatar.avatar.run import RunFolder
from rmavatar.utils import UserError, atomic_path
from rmavatar.utils.device import constant


def finite_flag(*tensors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ok, bad) on the tensors' device: ok (bool) = every element of every tensor is finite; bad is
    the float32 1.0 - ok. No host sync.

    The sum of the L1 norms is NaN or +Inf when any element is (or when finite values overflow: also
    worth skipping), so this is one fused reduction over all tensors, their sum, and one comparison:
    a sum of norms is never negative, and NaN < Inf is false (isfinite + all would take five)."""
    if not tensors:
        ok = torch.ones((), dtype=torch.bool)
    else:
        ok = torch.stack(torch._foreach_norm([t.detach() for t in tensors], 1)).sum() < math.inf
    dev = ok.device
    return ok, torch.where(ok, constant(0.0, torch.float32, dev), constant(1.0, torch.float32, dev))


class NonFiniteGuard:
    """Counts skipped (non-finite) steps on the device; :meth:`check` reads them at logging time and
    stops the run after ``max_bad_steps`` consecutive ones (the model is untouched by skipped steps)."""

    def __init__(self, device: torch.device, max_bad_steps: int):
        self.max_bad_steps = max_bad_steps
        self.skipped = torch.zeros((), device=device)  # since the last check
        self.run = torch.zeros((), device=device)  # current streak
        self.longest = torch.zeros((), device=device)  # longest streak since the last check

    def update(self, bad: torch.Tensor) -> None:
        """``bad``: 1.0 for a skipped step, 0.0 for an applied one (a float tensor on the device)."""
        bad = bad.to(self.run.dtype)
        self.skipped += bad
        torch.addcmul(bad, self.run, bad, out=self.run)  # (run + 1) * bad, as bad is 0 or 1
        torch.maximum(self.longest, self.run, out=self.longest)

    def counters(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.skipped, self.longest

    def check(self, skipped: int, longest: int, it: int, bar, writer, save: Callable[[], None],
              checkpoint) -> None:
        """Report the skipped steps; after ``max_bad_steps`` in a row, ``save()`` and stop the run."""
        if skipped:
            bar.write(f"iteration {it}: {skipped} step(s) since the last report skipped (non-finite loss or "
                      f"gradient; longest streak {longest})")
            if writer:
                writer.add_scalar("train/skipped_steps", skipped, it)
        self.skipped.zero_()
        self.longest.copy_(self.run)
        if longest >= self.max_bad_steps:
            save()
            raise UserError(
                f"training stopped at iteration {it}: {longest} consecutive steps had a non-finite loss or "
                f"gradient (log.max_bad_steps is {self.max_bad_steps}, checked at each progress report); "
                f"the last good model is saved in {checkpoint} (try a lower learning rate or check the data)")


class Reporter:
    """The progress bar, TensorBoard and the preview images of one run (a context manager around the
    loop); ``history`` gets one entry per progress report: iteration, loss, psnr, gaussians."""

    def __init__(self, log, run: RunFolder, total: int, start: int, progress: bool, headline: str = ""):
        self.log, self.run, self.total, self.progress = log, run, total, progress
        self.start, self.headline = start, headline
        self.history: list[dict] = []
        self.writer = self.bar = None

    def __enter__(self) -> "Reporter":
        from tqdm import tqdm

        if self.progress and self.headline:
            print(self.headline, flush=True)
        if self.log.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(self.run.tensorboard))
        self.bar = tqdm(total=self.total, initial=self.start, disable=not self.progress, unit="it",
                        dynamic_ncols=True, desc="train")
        return self

    def __exit__(self, *exc) -> bool:
        self.bar.close()
        if self.writer:
            self.writer.close()
        return False

    def step(self, it: int, out: dict, gaussians: int, guard: NonFiniteGuard, save: Callable[[], None]) -> None:
        """After iteration ``it``: progress, TensorBoard and previews from the step's values ``out``."""
        log, writer = self.log, self.writer
        self.bar.update(1)
        last = it == self.total
        log_progress = it % log.progress_every == 0 or last
        log_tb = writer is not None and it % log.tensorboard_every == 0
        if writer:
            for k, v in out["events"].items():  # density control: cloned / split / pruned counts, resets
                writer.add_scalar(f"density/{k}", float(v), it)
        if not (log_progress or log_tb):
            return
        names = [k for k, v in out.items() if torch.is_tensor(v) and v.dim() == 0 and k != "ok"]
        psnr = -10.0 * torch.log10(torch.mean((out["image"] - out["target"]) ** 2).clamp_min(1e-12))
        values = torch.stack([out[k].float() for k in names] + [psnr.float(), out["ok"].float(), *guard.counters()])
        *scalars, psnr_v, ok_v, skipped, longest = values.tolist()
        scalars = dict(zip(names, scalars), psnr=psnr_v, lr_position=out["lr_position"])
        guard.check(int(skipped), int(longest), it, self.bar, writer, save, self.run.checkpoint)
        if log_progress and ok_v:
            self.history.append({"iteration": it, "loss": scalars["loss"], "psnr": psnr_v, "gaussians": gaussians})
            self.bar.set_postfix(loss=f"{scalars['loss']:.4f}", psnr=f"{psnr_v:.2f}", N=gaussians, refresh=False)
        if log_tb and ok_v:
            for k, v in scalars.items():
                writer.add_scalar(f"train/{k}", v, it)
            writer.add_scalar("train/gaussians", gaussians, it)
        if it % log.preview_every == 0 or last:
            self.preview(out["image"], out["target"], it)

    def preview(self, image: torch.Tensor, target: torch.Tensor, it: int) -> None:
        from PIL import Image

        pair = torch.cat((image, target), dim=1).clamp(0, 1)
        arr = (pair.cpu().numpy() * 255.0 + 0.5).astype(np.uint8)  # numpy and PIL need host memory
        self.run.previews.mkdir(exist_ok=True)
        with atomic_path(self.run.previews / f"iter_{it:06d}.png") as tmp:
            Image.fromarray(arr).save(tmp, format="PNG")
        if self.writer:
            self.writer.add_image("preview/render_target", arr, it, dataformats="HWC")

    def summary(self, done: int, seconds: float, gaussians: int, pose_error: dict | None) -> None:
        """The closing lines of a run that reached its end."""
        if not self.progress:
            return
        last = f", last training PSNR {self.history[-1]['psnr']:.2f} dB" if self.history else ""
        print(f"done: {done} iterations in {seconds:.0f} s ({done / max(seconds, 1e-9):.2f} it/s), "
              f"{gaussians} Gaussians{last}; checkpoint {self.run.checkpoint}")
        if pose_error is not None:
            e = pose_error
            refined = "" if e["refined"] is None else f", refined {e['refined']['joint_angle_deg']:.2f}"
            print(f"training pose error vs the true poses (mean per-joint angle, deg): given "
                  f"{e['given']['joint_angle_deg']:.2f}{refined} -> {self.run.pose_error}")

"""The training frames as a step reads them: the order (:class:`FrameSampler`), the background of a step
(:func:`background_color`) and everything per frame that stays fixed for many steps (:class:`FrameCache`).

The posed body of every training frame is computed once, up front, in batches, and so are (while they fit
in the cache's budget) each frame's face table (the mesh half of posing the Gaussians) and, with a fixed
background, its composited target and the target's LPIPS features; a step then only runs avatar ->
rasterizer -> losses. Each saves a step dozens of tensor operations (GPU kernel launches).

So are the LPIPS windows (``loss.lpips_region: person``): one window size for the whole run, the largest
padded mask box of any training frame (:func:`lpips_window_size`), placed around each frame's own box on
AlexNet's 16-pixel grid (:func:`place_window`) and kept as index tensors, so a step crops with tensor
indexing and its shapes never depend on the frame (a step can be captured once and replayed).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from rmavatar.avatar.model import FACE_TABLE
from rmavatar.body import PoseSequence, posed_vertices
from rmavatar.render.camera import CameraTensors
from rmavatar.render.composite import composite
from rmavatar.train.losses import Window, lpips_units
from rmavatar.utils import UserError
from rmavatar.utils.device import constant

# Per-frame constants kept on the device for the whole run, while all of them together fit in this many
# bytes (filled in this order, each kind for every frame or not at all): face tables, composited targets,
# the targets' LPIPS features.
FRAME_CACHE_BYTES = 2 * 2**30

# The LPIPS window: a mask box (pixels with mask >= MASK_THRESHOLD: half-covered pixels and more, so faint
# soft-mask noise far from the person does not stretch the box) grows on each side by the larger of
# WINDOW_PAD of its side and WINDOW_PAD_MIN pixels (AlexNet's first layers see 11+ pixels around each
# output, and a render's stray Gaussians just outside the silhouette should still be seen); the run's
# window side is a multiple of WINDOW_MULTIPLE (AlexNet's stride 4 and two stride-2 pools) and at least
# WINDOW_MIN pixels, but never more than the image.
MASK_THRESHOLD = 0.5
WINDOW_PAD = 0.08
WINDOW_PAD_MIN = 16
WINDOW_MULTIPLE = 8
WINDOW_MIN = 64
# A window starts on this grid where it can: AlexNet's stride at its third to fifth layers (4 x the two
# pools' 2 x 2), so the window's features are the whole frame's features at the same places (a window
# 1 px off samples every layer elsewhere), except near the window's edges, whose receptive fields reach
# past it.
WINDOW_ALIGN = 16


def open_dataset(data):
    """The training dataset of ``data`` (a DataConfig), keeping every decoded training frame (image + mask,
    float32) in memory when that fits in 6 GB: re-reading large PNGs each step would cost more than a GPU
    step."""
    from rmavatar.data import load_dataset

    dataset = load_dataset(data.path, size=data.size)
    w, h = dataset.image_size
    dataset.reserve_cache(min(dataset.num_frames(data.split) * w * h * 16 / 2**20 + 64, 6144))
    return dataset


class FrameSampler:
    """Seeded shuffling, one frame per step: epoch e visits permutation(seed, e) in order.

    Its whole state is (epoch, position), so a checkpoint can store and restore it exactly.
    """

    def __init__(self, num_frames: int, seed: int):
        if num_frames < 1:
            raise UserError("the training split has no frames")
        self.num_frames = num_frames
        self.seed = seed
        self.epoch = 0
        self.position = 0
        self._perm = self._permutation(0)

    def _permutation(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(self.num_frames)

    def next(self) -> int:
        if self.position >= self.num_frames:
            self.epoch += 1
            self.position = 0
            self._perm = self._permutation(self.epoch)
        i = int(self._perm[self.position])
        self.position += 1
        return i

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "position": self.position, "num_frames": self.num_frames, "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        if state["num_frames"] != self.num_frames:
            raise UserError(f"the checkpoint was trained on {state['num_frames']} frames, "
                            f"the dataset now has {self.num_frames}")
        self.seed = state["seed"]
        self.epoch = state["epoch"]
        self.position = state["position"]
        self._perm = self._permutation(self.epoch)


def background_color(kind: str, generator: torch.Generator, device: torch.device | str = "cpu") -> torch.Tensor:
    """Background [3] on ``device`` for one step: white, black (shared read-only constants, not made and
    uploaded every step), or a random colour per step (drawn from ``generator``, on the CPU)."""
    if kind == "white":
        return constant((1.0, 1.0, 1.0), torch.float32, device)
    if kind == "black":
        return constant((0.0, 0.0, 0.0), torch.float32, device)
    return torch.rand(3, generator=generator).to(device, non_blocking=True)


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) of the pixels of ``mask`` [H,W] >= MASK_THRESHOLD, bottom and right
    exclusive; None when there are none."""
    on = np.asarray(mask) >= MASK_THRESHOLD
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    if rows.size == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def lpips_window_size(boxes: list[tuple[int, int, int, int] | None], height: int, width: int) -> tuple[int, int]:
    """The run's LPIPS window (h, w): the largest padded box of ``boxes`` (mask_box of each frame; None:
    an empty mask) in each direction, rounded up to a multiple of WINDOW_MULTIPLE, at least WINDOW_MIN
    (or the image side, when smaller), at most the image's ``height`` x ``width``."""
    def side(extent: int, image: int) -> int:
        padded = extent + 2 * max(math.ceil(WINDOW_PAD * extent), WINDOW_PAD_MIN)
        return min(max(-(-padded // WINDOW_MULTIPLE) * WINDOW_MULTIPLE, WINDOW_MIN), image)

    found = [b for b in boxes if b is not None]
    h = max((side(b[1] - b[0], height) for b in found), default=0)
    w = max((side(b[3] - b[2], width) for b in found), default=0)
    return max(h, min(WINDOW_MIN, height)), max(w, min(WINDOW_MIN, width))


def place_window(box: tuple[int, int, int, int] | None, size: tuple[int, int], height: int,
                 width: int) -> tuple[int, int]:
    """(top, left) of a ``size`` (h, w) window around ``box`` (mask_box; None: the image's centre) inside
    the ``height`` x ``width`` image: centred on the box, shifted inside the image, then moved to the
    nearest multiple of WINDOW_ALIGN that still holds the box (where one does). A box no larger than the
    window is inside it wherever the image's edge pushed it."""
    h, w = size
    top, bottom, left, right = box if box is not None else (height // 2, height // 2, width // 2, width // 2)
    return _window_start(top, bottom, h, height), _window_start(left, right, w, width)


def _window_start(lo: int, hi: int, n: int, image: int) -> int:
    """Start of an ``n``-pixel window on [0, image) holding [lo, hi): centred, inside, aligned if it can."""
    start = min(max((lo + hi - n) // 2, 0), image - n)
    down = start // WINDOW_ALIGN * WINDOW_ALIGN
    for aligned in sorted((down, down + WINDOW_ALIGN), key=lambda a: abs(a - start)):
        if aligned <= lo and hi <= aligned + n <= image:
            return aligned
    return start


class FrameCache:
    """The n training frames of ``split`` on ``device``: ``cameras`` (CameraTensors), the held bodies
    (``vertices`` [n,V,3], ``body_pose`` [n,69]: what every step without per-step pose corrections uses),
    the LPIPS windows (``window_rows`` [n,h], ``window_cols`` [n,w]; None: LPIPS on the whole frame) and,
    within a byte budget (:meth:`fill`), ``masks`` [n,H,W,1] (for a mask loss), ``face_tables``
    [n,Fb,38], ``targets`` [n,H,W,3] and the targets' LPIPS features (None where they did not fit:
    computed at each step instead)."""

    def __init__(self, dataset, split: str, body, device: torch.device):
        self.dataset, self.split, self.body, self.device = dataset, split, body, device
        cams = [dataset.camera(split, i) for i in range(dataset.num_frames(split))]
        viewmats = torch.as_tensor(np.stack([c.viewmat for c in cams]), dtype=torch.float32, device=device)
        Ks = torch.as_tensor(np.stack([c.K for c in cams]), dtype=torch.float32, device=device)
        self.width, self.height = cams[0].width, cams[0].height
        self.cameras = [CameraTensors(v, k, self.width, self.height) for v, k in zip(viewmats, Ks)]
        self.avatar = self.face_tables = self.targets = self.target_units = self._cached_bg = None
        self.window_rows = self.window_cols = self.masks = None

    def __len__(self) -> int:
        return len(self.cameras)

    def hold(self, poses: PoseSequence, pose_input: Callable) -> None:
        """Pose every frame's body once for ``poses``: ``vertices``, ``body_pose`` (the rectifier's pose
        input, ``pose_input(body_pose, hand_pose)``: the avatar's ``Avatar.pose_input``) and the face
        tables, when cached."""
        betas = self.dataset.params(self.split)["betas"]
        self.vertices = posed_vertices(self.body, poses, betas).to(self.device)
        self.body_pose = pose_input(poses.body_pose, poses.hand_pose).to(self.device)
        if self.face_tables is not None:
            self.face_tables = self._face_tables()

    def fill(self, avatar, background: str, lpips: bool, generator: torch.Generator, budget: int,
             lpips_region: str = "frame", masks: bool = False) -> None:
        """With ``lpips`` and ``lpips_region`` "person" (the run's ``loss.lpips_region``), the frames' LPIPS
        windows (:meth:`lpips_window`); then cache within ``budget`` bytes, in this order: with ``masks``
        (a mask loss) the frames' masks; the face tables of ``avatar``; with a fixed ``background`` the
        composited targets; with ``lpips`` their LPIPS features (of their windows)."""
        n = len(self)
        self.avatar = avatar
        if lpips and lpips_region == "person":
            self._make_windows()
        need = n * self.height * self.width * 4
        if masks and need <= budget:
            self.masks = torch.stack([self.mask(i) for i in range(n)])
            budget -= need
        need = n * avatar.binding_faces.shape[0] * FACE_TABLE * self.vertices.element_size()
        if need <= budget:
            self.face_tables = self._face_tables()
            budget -= need
        if background not in ("white", "black"):
            return  # a new random background every step: nothing fixed to keep
        bg = background_color(background, generator, self.device)
        need = n * self.height * self.width * 3 * 4
        if need > budget:
            return
        self.targets = torch.stack([self.target(i, bg) for i in range(n)])
        self._cached_bg = bg
        budget -= need
        if lpips:
            first = lpips_units(self.targets[0], self.lpips_window(0))
            if n * sum(u.numel() * u.element_size() for u in first) <= budget:
                self.target_units = [first] + [lpips_units(t, self.lpips_window(i))
                                               for i, t in enumerate(self.targets[1:], 1)]

    def _make_windows(self) -> None:
        """``window_rows`` [n,h] and ``window_cols`` [n,w] (long, on the device) from every frame's mask:
        one size for all (:func:`lpips_window_size`), each placed around its own frame's box."""
        boxes = [mask_box(self.dataset.frame(self.split, i).mask) for i in range(len(self))]
        size = lpips_window_size(boxes, self.height, self.width)
        corners = [place_window(box, size, self.height, self.width) for box in boxes]
        rows = torch.tensor([r0 for r0, _ in corners], dtype=torch.long)[:, None] + torch.arange(size[0])
        cols = torch.tensor([c0 for _, c0 in corners], dtype=torch.long)[:, None] + torch.arange(size[1])
        self.window_rows, self.window_cols = rows.to(self.device), cols.to(self.device)

    def lpips_window(self, i: int) -> Window | None:
        """Frame ``i``'s LPIPS window (rows [h], cols [w]: long on the device, one size for every frame),
        for ``total_loss(lpips_window=)`` (and ``lpips_units``), or None: LPIPS on the whole frame."""
        return None if self.window_rows is None else (self.window_rows[i], self.window_cols[i])

    @torch.no_grad()
    def _face_tables(self) -> torch.Tensor:
        """The held bodies' face tables [n,Fb,38], one frame at a time: the same arithmetic, to the bit,
        as an uncached step's."""
        return torch.stack([self.avatar.face_table(v) for v in self.vertices])

    def held(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Frame ``i``'s held body: vertices [V,3], the rectifier's pose input and its face table (None:
        not cached)."""
        return self.vertices[i], self.body_pose[i], None if self.face_tables is None else self.face_tables[i]

    def target(self, i: int, bg: torch.Tensor) -> torch.Tensor:
        """Frame ``i``'s image composited over the background ``bg`` [3]: [H,W,3] on the device."""
        if self.targets is not None and bg is self._cached_bg:
            return self.targets[i]
        frame = self.dataset.frame(self.split, i)
        image = torch.from_numpy(np.array(frame.image, dtype=np.float32)).to(self.device)
        mask = torch.from_numpy(np.array(frame.mask, dtype=np.float32)).to(self.device)
        return composite(image, mask, bg)

    def mask(self, i: int) -> torch.Tensor:
        """Frame ``i``'s person mask [H,W,1] on the device (float32, 0..1)."""
        if self.masks is not None:
            return self.masks[i]
        mask = np.array(self.dataset.frame(self.split, i).mask, dtype=np.float32)
        return torch.from_numpy(mask).to(self.device).unsqueeze(-1)

    def lpips_units(self, i: int, bg: torch.Tensor) -> list[torch.Tensor] | None:
        """The cached LPIPS features of ``target(i, bg)`` cropped to ``lpips_window(i)`` (for
        ``total_loss(lpips_units=, lpips_window=)``), or None."""
        return self.target_units[i] if self.target_units is not None and bg is self._cached_bg else None

    def frames(self):
        """The dataset's training frames (image, mask, camera), for pose fits."""
        return self.dataset.frames(self.split, len(self))

    def fit_background(self, background: str) -> torch.Tensor:
        """The fixed background pose fits composite over: the run's, or white when it is random (any
        fixed one does: the targets are composited with their masks over the same one)."""
        return background_color("black" if background == "black" else "white", None, self.device)

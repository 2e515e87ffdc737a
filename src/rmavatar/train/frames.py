"""The training frames as a step reads them: the order (:class:`FrameSampler`), the background of a step
(:func:`background_color`) and everything per frame that stays fixed for many steps (:class:`FrameCache`).

The posed body of every training frame is computed once, up front, in batches, and so are (while they fit
in the cache's budget) each frame's face table (the mesh half of posing the Gaussians) and, with a fixed
background, its composited target and the target's LPIPS features; a step then only runs avatar ->
rasterizer -> losses. Each saves a step dozens of tensor operations (GPU kernel launches).
"""

from __future__ import annotations

import numpy as np
import torch

from rmavatar.avatar.model import FACE_TABLE
from rmavatar.body import PoseSequence, posed_vertices
from rmavatar.render.camera import CameraTensors
from rmavatar.render.composite import composite
from rmavatar.train.losses import lpips_units
from rmavatar.utils import UserError
from rmavatar.utils.device import constant

# Per-frame constants kept on the device for the whole run, while all of them together fit in this many
# bytes (filled in this order, each kind for every frame or not at all): face tables, composited targets,
# the targets' LPIPS features.
FRAME_CACHE_BYTES = 2 * 2**30


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


class FrameCache:
    """The n training frames of ``split`` on ``device``: ``cameras`` (CameraTensors), the held bodies
    (``vertices`` [n,V,3], ``body_pose`` [n,69]: what every step without per-step pose corrections uses)
    and, within a byte budget (:meth:`fill`), ``face_tables`` [n,Fb,38], ``targets`` [n,H,W,3] and the
    targets' LPIPS features (None where they did not fit: computed at each step instead)."""

    def __init__(self, dataset, split: str, body, device: torch.device):
        self.dataset, self.split, self.body, self.device = dataset, split, body, device
        cams = [dataset.camera(split, i) for i in range(dataset.num_frames(split))]
        viewmats = torch.as_tensor(np.stack([c.viewmat for c in cams]), dtype=torch.float32, device=device)
        Ks = torch.as_tensor(np.stack([c.K for c in cams]), dtype=torch.float32, device=device)
        self.width, self.height = cams[0].width, cams[0].height
        self.cameras = [CameraTensors(v, k, self.width, self.height) for v, k in zip(viewmats, Ks)]
        self.avatar = self.face_tables = self.targets = self.target_units = self._cached_bg = None

    def __len__(self) -> int:
        return len(self.cameras)

    def hold(self, poses: PoseSequence) -> None:
        """Pose every frame's body once for ``poses``: ``vertices``, ``body_pose`` (and the face tables,
        when cached)."""
        betas = self.dataset.params(self.split)["betas"]
        self.vertices = posed_vertices(self.body, poses, betas).to(self.device)
        self.body_pose = poses.body_pose.to(self.device)
        if self.face_tables is not None:
            self.face_tables = self._face_tables()

    def fill(self, avatar, background: str, lpips: bool, generator: torch.Generator, budget: int) -> None:
        """Cache within ``budget`` bytes, in this order: the face tables of ``avatar``; with a fixed
        ``background`` the composited targets; with ``lpips`` their LPIPS features."""
        n = len(self)
        self.avatar = avatar
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
            first = lpips_units(self.targets[0])
            if n * sum(u.numel() * u.element_size() for u in first) <= budget:
                self.target_units = [first] + [lpips_units(t) for t in self.targets[1:]]

    @torch.no_grad()
    def _face_tables(self) -> torch.Tensor:
        """The held bodies' face tables [n,Fb,38], one frame at a time: the same arithmetic, to the bit,
        as an uncached step's."""
        return torch.stack([self.avatar.face_table(v) for v in self.vertices])

    def held(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Frame ``i``'s held body: vertices [V,3], body_pose [69] and its face table (None: not cached)."""
        return self.vertices[i], self.body_pose[i], None if self.face_tables is None else self.face_tables[i]

    def target(self, i: int, bg: torch.Tensor) -> torch.Tensor:
        """Frame ``i``'s image composited over the background ``bg`` [3]: [H,W,3] on the device."""
        if self.targets is not None and bg is self._cached_bg:
            return self.targets[i]
        frame = self.dataset.frame(self.split, i)
        image = torch.from_numpy(np.array(frame.image, dtype=np.float32)).to(self.device)
        mask = torch.from_numpy(np.array(frame.mask, dtype=np.float32)).to(self.device)
        return composite(image, mask, bg)

    def lpips_units(self, i: int, bg: torch.Tensor) -> list[torch.Tensor] | None:
        """The cached LPIPS features of ``target(i, bg)`` (for ``total_loss(lpips_units=)``), or None."""
        return self.target_units[i] if self.target_units is not None and bg is self._cached_bg else None

    def frames(self):
        """The dataset's training frames (image, mask, camera), for pose fits."""
        return self.dataset.frames(self.split, len(self))

    def fit_background(self, background: str) -> torch.Tensor:
        """The fixed background pose fits composite over: the run's, or white when it is random (any
        fixed one does: the targets are composited with their masks over the same one)."""
        return background_color("black" if background == "black" else "white", None, self.device)

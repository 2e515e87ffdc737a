"""Mesh-embedded Gaussians with pose-conditioned rectification (paper §3.2-3.3; docs/model.md).

Every Gaussian belongs to one triangle (``face_ids``) and stores its attributes in that triangle's
local frame (units of the triangle scale w). Posing is a similarity transform per triangle:
mu* = w R mu + M, r* = quat(R) (x) r, s* = w exp(log_scale); the rectifier then adds
pose-dependent offsets: mu' = mu* + d_mu, r' = r* (x) normalize(1 + d_r), s' = s* + d_s.
The paper's rectifier reads the posed position and the whole pose and gives d_mu, d_s in world units;
the "local" one reads the rest-pose position and the pose of the joints that skin the Gaussian's
triangle, and gives d_mu = w R d, d_s = w d' from outputs d, d' in the triangle's frame. Each design is
a class (``rectifier.PaperRectifier``, ``rectifier.LocalRectifier``) that the avatar asks.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import nn

from rmavatar.avatar.compose import compose_gaussians
from rmavatar.avatar.geometry import FaceTable, face_table, same_quads, triangle_frames
from rmavatar.avatar.rectifier import DESIGNS, POSE_DIM, PRECISIONS, rectifier_design, window_alpha
from rmavatar.avatar.rows import RowGathers, frame_points, posed_rows
from rmavatar.body.base import HAND_POSE_DIM
from rmavatar.render.gaussians import GaussianSet
from rmavatar.render.kernels import ALPHA_MIN
from rmavatar.utils import UserError
from rmavatar.utils.config import check_fields
from rmavatar.utils.device import host_scalar, set_host_scalar

RECTIFIERS = tuple(DESIGNS)  # model.rectifier designs (False: no rectifier)
SH_C0 = 0.28209479177387814  # Y_0^0; colour = 0.5 + SH_C0 * dc (3DGS / gsplat convention)

FACE_TABLE = FaceTable.WIDTH  # columns of Avatar.face_table (named by geometry.FaceTable)
# The per-Gaussian parameters, in the order density control and checkpoints see them.
GAUSSIAN_PARAMS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


@dataclass
class AvatarConfig:
    """How the avatar is built; ``build(body)`` makes it (``TrainConfig.model`` is this config).

    ``placement``: "face" = one Gaussian per binding face (the paper); "area" = ``num_gaussians`` in
    total, at least one per face, the rest given out by triangle area (a body's faces can differ much in
    size), placed uniformly inside their triangle. ``body``/``gender`` name the body model the avatar is
    bound to (None: the dataset's own preset and gender)."""

    # The body model the avatar is bound to: "anny", "anny:PRESET", "smpl:PATH"; None = the dataset's own.
    body: str | None = None
    gender: str | None = None  # the body model's gender; None = the dataset's
    sh_degree: int = 3  # highest SH degree stored (0..3)
    # The rectifier design (rectifier.DESIGNS), the pose-conditioned MLP's offsets:
    # "paper": F(gamma(posed world position), all 69 pose values) -> world-space offsets (paper §3.3);
    # "local": F(gamma(rest-pose position), the pose of the joints skinning the Gaussian's triangle) ->
    # offsets in the triangle's frame, in units of its scale w, so they turn and grow with the body;
    # False = the paper's "w/o GauRec": Gaussians fixed to their faces. (Older configs' true is read as
    # "paper" by the migration chain, rmavatar.avatar.run.)
    # "local" is the default for its results on held-out and new poses (docs/model.md).
    rectifier: bool | str = "local"
    # "local": a face's Gaussians see joint j's pose when j's skinning weight on one of the face's
    # corners exceeds this.
    rectifier_mask_threshold: float = 0.01
    # The rectifier also sees the 90 finger pose values (its pose input is body_pose then hand_pose, 159
    # values; "local": a hand's faces see the finger joints that skin them). For data with finger poses;
    # needs a body with fingers (Anny, or an SMPL-H / SMPL-X file).
    hand_pose: bool = False
    num_freqs: int = 6  # frequency bands of the rectifier's positional encoding (6 * num_freqs channels)
    hidden: int = 128  # width of the rectifier MLP's hidden layers
    # Arithmetic of the rectifier's hidden layers: "float32"; "bfloat16" (faster on CPUs with bf16 dot
    # products, AVX512-BF16 / AMX, at about 3 significant digits: the same avatars, docs/model.md); or
    # "auto", bfloat16 where the CPU has those products and float32 elsewhere (GPUs included). Outputs
    # and gradients stay float32.
    rectifier_precision: str = "auto"
    init_opacity: float = 0.1  # every Gaussian's opacity at the start, in (0, 1)
    init_color: tuple[float, float, float] = (0.5, 0.5, 0.5)  # every Gaussian's start RGB (unless build's init_colors)
    placement: str = "face"  # where Gaussians start: "face" (one per binding face) or "area" (see above)
    num_gaussians: int | None = None  # total budget for placement="area"
    # The rectified scale s* + d_s is clamped to this (metres): d_s is additive and may overshoot.
    min_scale: float = 1e-6
    # Coarse-to-fine encoding window (HumanNeRF): closed until c2f_start, fully open at c2f_end,
    # both as fractions of the run (set_progress). Our choice; the paper gives no values.
    coarse_to_fine: bool = True  # open the encoding's bands gradually (False: all open from the start)
    c2f_start: float = 0.0  # fraction of the run at which the window starts to open
    c2f_end: float = 0.5  # fraction of the run at which the window is fully open
    # SH bands switch on one at a time every sh_every_frac of the run (3DGS: 1000 of 50,000 iterations).
    sh_every_frac: float = 0.02

    def __post_init__(self):
        self.validate()

    def validate(self) -> "AvatarConfig":
        """Raise UserError for values no avatar can use (names are the config.yaml keys); returns self."""
        check_fields(self, "model", positive=("hidden", "min_scale"), nonnegative=("sh_every_frac",))
        if not 0 <= self.sh_degree <= 3:
            raise UserError(f"model.sh_degree must be 0..3, got {self.sh_degree}")
        if self.placement not in ("face", "area"):
            raise UserError(f"model.placement must be 'face' or 'area', not {self.placement!r}")
        if self.placement == "area" and not self.num_gaussians:
            raise UserError("model.placement 'area' needs model.num_gaussians (the total Gaussian budget)")
        if not 0.0 < self.init_opacity < 1.0:
            raise UserError(f"model.init_opacity must be in (0, 1), got {self.init_opacity}")
        if self.rectifier is not False and self.rectifier not in RECTIFIERS:
            raise UserError(f"model.rectifier must be one of {', '.join(RECTIFIERS)} or false (no rectifier), "
                            f"not {self.rectifier!r}")
        if not 0.0 <= self.rectifier_mask_threshold < 1.0:
            raise UserError(f"model.rectifier_mask_threshold must be in [0, 1), got {self.rectifier_mask_threshold}")
        if self.num_freqs < 1:
            raise UserError(f"model.num_freqs must be >= 1, got {self.num_freqs}")
        if self.rectifier_precision not in PRECISIONS:
            raise UserError(f"model.rectifier_precision must be one of {', '.join(PRECISIONS)}, "
                            f"not {self.rectifier_precision!r}")
        self.init_color = tuple(float(c) for c in self.init_color)
        if len(self.init_color) != 3:
            raise UserError(f"model.init_color must have 3 values, got {self.init_color}")
        return self

    def build(self, body, seed: int = 0, init_colors=None) -> "Avatar":
        """The avatar on ``body`` (a BodyModel: its faces, binding_faces, v_template, and joint_weights
        for the local rectifier); ``seed`` draws the in-triangle positions of area placement;
        ``init_colors`` [3] or [F,3] per face."""
        return Avatar(body.faces, getattr(body, "binding_faces", None), body.v_template, self, init_colors,
                      seed=seed, joint_weights=self.body_joint_weights(body), relaxed_hand_pose=self.relaxed_hands(body))

    def body_joint_weights(self, body) -> torch.Tensor | None:
        """What the avatar needs of ``body``'s skinning weights: [V,24] for a design that masks the pose
        by them (the local rectifier; [V,54] with ``hand_pose``: the finger joints apart), else None."""
        design = rectifier_design(self.rectifier)
        if design is None or not design.needs_joint_weights:
            return None
        return body.joint_weights(hands=True) if self.hand_pose else body.joint_weights()

    def relaxed_hands(self, body) -> torch.Tensor | None:
        """``body``'s relaxed hand pose [90] (what the rectifier sees where no hand pose is given) with
        ``hand_pose``, else None; UserError for a body without fingers."""
        if not self.hand_pose or self.rectifier is False:
            return None
        if getattr(body, "relaxed_hand_pose", None) is None:
            raise UserError(f"model.hand_pose needs a body with fingers (anny, or an SMPL-H / SMPL-X file); "
                            f"{body.spec} has none")
        return body.relaxed_hand_pose.detach().cpu()


@dataclass
class AvatarExtras:
    """What the training losses read of a posed avatar besides its Gaussians (``forward_with_extras``)."""

    local_means: torch.Tensor  # [N,3] face-local positions (units of w): the position regulariser's input
    local_log_scales: torch.Tensor  # [N,3] face-local log-scales: the scaling regulariser's input
    # the rectifier's offsets (d_mu, d_s, d_r) in world units (the offset regulariser's input); None without one
    offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None
    # [N] each row's weight in the regularisers' means: 1/live rows for a live row, 0 for an unused one, in
    # capacity buffers (Avatar.row_weights); None: every row counts, 1/N
    row_weights: torch.Tensor | None = None


def _triangle_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    tri = vertices[faces]
    return 0.5 * torch.linalg.vector_norm(
        torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1), dim=-1
    )


def area_counts(areas: torch.Tensor, total: int) -> torch.Tensor:
    """Gaussians per face [F]: one each, the remaining ``total - F`` shared by area (largest remainder)."""
    n = areas.shape[0]
    if total < n:
        raise UserError(f"num_gaussians ({total}) must be at least the number of binding faces ({n})")
    extra = total - n
    share = areas.double() / areas.double().sum().clamp_min(1e-30) * extra
    base = share.floor().long()
    left = extra - int(base.sum())
    if left > 0:
        base[torch.argsort(share - base.double(), descending=True)[:left]] += 1
    return base + 1


def _mesh_tensors(faces, binding_faces, v_template):
    """faces [F,3] long, binding_faces [Fb] long (None: every face) and v_template [V,3] float32, checked."""
    faces = torch.as_tensor(faces, dtype=torch.long)
    v_template = torch.as_tensor(v_template, dtype=torch.float32)
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise UserError(f"faces must be [F,3], got {tuple(faces.shape)}")
    if v_template.dim() != 2 or v_template.shape[1] != 3:
        raise UserError(f"v_template must be [V,3], got {tuple(v_template.shape)}")
    if binding_faces is None:
        binding_faces = torch.arange(faces.shape[0])
    binding_faces = torch.as_tensor(binding_faces, dtype=torch.long)
    if binding_faces.numel() == 0:
        raise UserError("the body model has no binding faces to attach Gaussians to")
    return faces, binding_faces, v_template


def _initial_layout(v_template, faces, binding_faces, config, seed):
    """The Gaussians' faces [N], local means [N,3] and log-scales [N,3] at the start (``config.placement``)."""
    bf = binding_faces
    if config.placement == "face":
        face_ids = bf.clone()
        means = torch.zeros(bf.shape[0], 3)
        log_scales = torch.zeros(bf.shape[0], 3)
        return face_ids, means, log_scales
    counts = area_counts(_triangle_areas(v_template, faces[bf]), int(config.num_gaussians))
    face_ids = torch.repeat_interleave(bf, counts)
    gen = torch.Generator().manual_seed(seed)
    # Uniform points in the triangle (square-root barycentric sampling), then to local coordinates.
    u = torch.rand(face_ids.shape[0], 2, generator=gen)
    su = u[:, 0].sqrt()
    bary = torch.stack((1 - su, su * (1 - u[:, 1]), su * u[:, 1]), dim=-1)
    # Faces with a single Gaussian keep it at the centroid, as the paper initialises.
    single = (counts == 1).repeat_interleave(counts)
    bary[single] = 1.0 / 3.0
    tri = v_template[faces[face_ids]]  # [N,3,3]
    points = (bary.unsqueeze(-1) * tri).sum(-2)
    R, w, M = triangle_frames(v_template, faces[face_ids])
    means = ((points - M).unsqueeze(-2) @ R).squeeze(-2) / w.clamp_min(1e-12).unsqueeze(-1)
    # k Gaussians share a triangle: each covers ~1/k of its area.
    log_scales = (-0.5 * torch.log(counts.float())).repeat_interleave(counts).unsqueeze(-1).expand(-1, 3)
    return face_ids, means, log_scales.contiguous()


def _initial_colors(init_colors, default, face_ids, num_faces):
    """The Gaussians' start colours [N,3]: ``init_colors`` [3] or [F,3] (per face), or ``default`` [3]."""
    n = face_ids.shape[0]
    if init_colors is None:
        return torch.tensor(default, dtype=torch.float32).expand(n, 3).clone()
    c = torch.as_tensor(init_colors, dtype=torch.float32)
    if c.shape == (3,):
        return c.expand(n, 3).clone()
    if c.shape == (num_faces, 3):
        return c[face_ids].clone()
    raise UserError(f"init_colors must be [3] or [F={num_faces},3] (per face), got {tuple(c.shape)}")


class Avatar(nn.Module):
    """Gaussians embedded in the triangles of a body mesh, plus the rectification MLP.

    Build with ``AvatarConfig.build(body)`` or ``Avatar(faces, binding_faces, v_template, config)``.
    ``avatar(vertices [V,3], body_pose [69]) -> GaussianSet``.

    Parameters (per Gaussian, names in GAUSSIAN_PARAMS; all in the parent triangle's frame):
    means [N,3] (units of w), quats [N,4] wxyz (unnormalised), log_scales [N,3], opacity_logits [N],
    sh_dc [N,1,3], sh_rest [N,K-1,3]. Buffers: face_ids [N] (index into ``faces``), faces [F,3],
    binding_faces [Fb], rest_face_scale [F] (w of every face on ``v_template``), rest_extent (half the
    rest mesh's bounding-box diagonal),
    active_sh_degree (grows during training like 3DGS). With the local rectifier (``joint_weights``
    [V,24], the body's skinning weights per SMPL joint, required): pose_masks [U,69] (the distinct
    sets of pose values faces see) and face_pose_group [F] (every face's row of pose_masks).
    ``rectifier``: the design (a ``rectifier.RectifierDesign``, which holds the MLP) or None.

    Capacity buffers (training on a GPU: shapes that stay fixed between density events, so a captured
    step stays valid): the per-Gaussian tensors have ``capacity`` rows of which the first
    ``num_gaussians`` are live; the rest are unused (opacity 0, no gradient). ``live_rows`` is then that
    count and the buffers ``live`` [C] (1 / 0) and ``row_weights`` [C] (``live / live_rows``) mask them;
    :func:`rmavatar.train.density.use_capacity` turns them on, density control rewrites rows in place,
    and :meth:`checkpoint_state` keeps only the live rows. ``live_rows`` None: every row is live.

    The rectifier's pose input (``body_pose`` in the methods below) has ``pose_dim`` values: body_pose
    [69], followed by hand_pose [90] when ``config.hand_pose`` (then pose_masks are [U,159] and
    ``relaxed_hand_pose`` [90] is the body's relaxed hands); :meth:`pose_input` builds it.
    """

    def __init__(
        self,
        faces: torch.Tensor,
        binding_faces: torch.Tensor | None,
        v_template: torch.Tensor,
        config: AvatarConfig | None = None,
        init_colors: torch.Tensor | None = None,
        seed: int = 0,
        joint_weights: torch.Tensor | None = None,
        relaxed_hand_pose: torch.Tensor | None = None,
    ):
        super().__init__()
        config = (config or AvatarConfig()).validate()
        self.config = config
        faces, binding_faces, v_template = _mesh_tensors(faces, binding_faces, v_template)
        self._init_mesh(faces, binding_faces, v_template)
        self._init_gaussians(v_template, config, init_colors, seed)
        self._init_rectifier(config, joint_weights, relaxed_hand_pose)
        self.live_rows: int | None = None  # capacity buffers (class docstring); None: every row is live
        self.register_buffer("live", None, persistent=False)
        self.register_buffer("row_weights", None, persistent=False)
        self.rows = RowGathers()  # the per-row gathers steps reuse (rmavatar.avatar.rows)

    def _init_mesh(self, faces, binding_faces, v_template):
        """The mesh buffers: the faces, the binding faces and what the rest mesh gives."""
        self.num_vertices = v_template.shape[0]
        self.register_buffer("faces", faces)
        self.register_buffer("binding_faces", binding_faces)
        _, w_rest, _ = triangle_frames(v_template, faces)
        self.register_buffer("rest_face_scale", w_rest)
        # Half the rest mesh's bounding-box diagonal: the "scene size" density control measures against.
        self.register_buffer("rest_extent", 0.5 * torch.linalg.vector_norm(v_template.amax(0) - v_template.amin(0)))
        self.register_buffer("active_sh_degree", torch.tensor(0, dtype=torch.long))
        # Rest-mesh frames of the binding faces (rest_means: the local rectifier's input); rebuilt from
        # the body, not stored.
        R, w, M = triangle_frames(v_template, faces[binding_faces])
        self.register_buffer("rest_frames", R, persistent=False)
        self.register_buffer("rest_scales", w, persistent=False)
        self.register_buffer("rest_centroids", M, persistent=False)

    def _init_gaussians(self, v_template, config, init_colors, seed):
        """The Gaussians' faces and parameters at the start (GAUSSIAN_PARAMS)."""
        face_ids, means, log_scales = _initial_layout(v_template, self.faces, self.binding_faces, config, seed)
        n = face_ids.shape[0]
        k = (config.sh_degree + 1) ** 2
        colors = _initial_colors(init_colors, config.init_color, face_ids, self.faces.shape[0])
        self.register_buffer("face_ids", face_ids)
        self.means = nn.Parameter(means)
        self.quats = nn.Parameter(torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1))
        self.log_scales = nn.Parameter(log_scales)
        p = config.init_opacity
        self.opacity_logits = nn.Parameter(torch.full((n,), math.log(p / (1 - p))))
        self.sh_dc = nn.Parameter(((colors - 0.5) / SH_C0).unsqueeze(1))
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3))

    def _init_rectifier(self, config, joint_weights, relaxed_hand_pose):
        """The rectifier design that ``config.rectifier`` names (None: none), and its pose masks."""
        design = rectifier_design(config.rectifier)
        hands = design is not None and config.hand_pose
        self.pose_dim = POSE_DIM + (HAND_POSE_DIM if hands else 0)
        if hands:
            if relaxed_hand_pose is None:
                raise UserError("model.hand_pose needs a body with fingers (anny, or an SMPL-H / SMPL-X file)")
            self.register_buffer("relaxed_hand_pose", torch.as_tensor(relaxed_hand_pose, dtype=torch.float32),
                                 persistent=False)
        self.rectifier = None if design is None else design(config.num_freqs, config.hidden, pose_dim=self.pose_dim,
                                                            precision=config.rectifier_precision)
        # Which pose values each face's Gaussians see, where the design masks the pose (buffers of the
        # avatar, so checkpoints keep them under "pose_masks" / "face_pose_group").
        masks = None if design is None else self.rectifier.make_pose_masks(
            self.faces, joint_weights, config.rectifier_mask_threshold, self.num_vertices)
        if masks is not None:
            self.register_buffer("pose_masks", masks[0])
            self.register_buffer("face_pose_group", masks[1])

    # ------------------------------------------------------------------ construction
    def checkpoint_state(self) -> dict:
        """Everything needed to rebuild this avatar: {"config": dict, "state_dict": tensors}; of capacity
        buffers only the live rows."""
        state = self.state_dict()
        if self.live_rows is not None:
            for name in (*GAUSSIAN_PARAMS, "face_ids"):
                state[name] = state[name][: self.live_rows].clone()
        return {"config": dataclasses.asdict(self.config), "state_dict": state}

    @classmethod
    def from_state(cls, body, state: dict, where: str = "checkpoint") -> "Avatar":
        """Rebuild from ``checkpoint_state()`` output for ``body`` (its mesh must match)."""
        try:
            config = AvatarConfig(**state["config"])
            sd = state["state_dict"]
            faces = sd["faces"]
        except (KeyError, TypeError) as exc:
            raise UserError(f"{where}: not an avatar state ({exc})") from None
        body_faces = torch.as_tensor(body.faces, dtype=torch.long)
        if faces.shape != body_faces.shape or not (torch.equal(faces.cpu(), body_faces.cpu())
                                                   or same_quads(faces, body_faces)):
            raise UserError(
                f"{where}: the avatar was trained on a different body mesh ({faces.shape[0]} faces) "
                f"than the body model given ({body_faces.shape[0]} faces)"
            )
        # the avatar's own triangulation (a body built on another machine may split a few quads otherwise)
        avatar = cls(faces.to(body_faces.device), getattr(body, "binding_faces", None), body.v_template,
                     dataclasses.replace(config, placement="face"), joint_weights=config.body_joint_weights(body),
                     relaxed_hand_pose=config.relaxed_hands(body))
        avatar.config = config
        try:
            avatar.load_state_dict(sd)
        except RuntimeError as exc:
            raise UserError(f"{where}: the avatar state does not fit this body model: {exc}") from None
        return avatar

    # ------------------------------------------------------------------ properties
    @property
    def num_gaussians(self) -> int:
        """The live Gaussians (all rows, unless in capacity buffers)."""
        return self.means.shape[0] if self.live_rows is None else self.live_rows

    @property
    def capacity(self) -> int:
        """Rows of the per-Gaussian tensors (``num_gaussians`` of them live)."""
        return self.means.shape[0]

    def opacities(self) -> torch.Tensor:
        """Every row's opacity [C] as drawn: the sigmoid of its logit, 0 for the unused rows of capacity
        buffers (culled, and no gradient reaches them)."""
        opacities = torch.sigmoid(self.opacity_logits)
        return opacities if self.live is None else opacities * self.live

    def set_frequency_alpha(self, alpha: float) -> None:
        """Coarse-to-fine encoding window position (0..num_freqs); see rectifier.window_alpha."""
        if self.rectifier is not None:
            self.rectifier.set_frequency_alpha(alpha)

    def set_progress(self, iteration: int, total: int) -> None:
        """Put the training-time schedules at ``iteration`` of ``total``: the active SH degree and
        the coarse-to-fine encoding window. Absolute (not incremental), so resuming is exact."""
        every = max(1, round(self.config.sh_every_frac * total))
        degree = min(self.config.sh_degree, iteration // every)
        set_host_scalar(self, "active_sh_degree", degree, int)
        if self.config.coarse_to_fine:
            start, end = self.config.c2f_start * total, self.config.c2f_end * total
            self.set_frequency_alpha(window_alpha(iteration, round(start), round(end), self.config.num_freqs))
        else:
            self.set_frequency_alpha(self.config.num_freqs)

    # ------------------------------------------------------------------ posing
    def posed(self, vertices: torch.Tensor | None, table: torch.Tensor | None = None):
        """Mesh-embedded (unrectified) world attributes: mu* [N,3], r* [N,4], s* [N,3] (``table``: as in
        :meth:`forward`)."""
        return compose_gaussians(self._posed(vertices, table), self.means, self.quats, self.log_scales)[:3]

    def rest_means(self) -> torch.Tensor:
        """Every Gaussian's position on the rest mesh [N,3] (the local rectifier's input)."""
        wR, M, _ = self.rows.local(self)
        return frame_points(wR, M, self.means)

    def face_slot(self) -> torch.Tensor:
        """Index of every Gaussian's face in ``binding_faces`` [N] (kept by :attr:`rows`)."""
        return self.rows.slot(self)

    def face_table(self, vertices: torch.Tensor, kernels: bool = False) -> torch.Tensor:
        """The frames of the binding faces of posed meshes ``vertices`` [V,3] or [B,V,3]:
        [Fb, FACE_TABLE] or [B, Fb, FACE_TABLE], per face the columns of :class:`FaceTable`: R, w R, M, w
        and L(quat(R)) (the matrix of r -> quat(R) (x) r), so that mu* and r* are one batched matrix
        product each.

        It depends on the mesh only, not on the Gaussians: training, which poses the same frames again
        and again, computes it once per frame and passes it to :meth:`forward` as ``table``.
        ``kernels``: one mesh on the CPU with gradients goes through the numba kernels of
        :func:`rmavatar.avatar.geometry.face_table` (pose fits ask for them; training does not, so that
        a run resumes to the same bits as the version that trained it)."""
        if vertices.dim() not in (2, 3) or vertices.shape[-2:] != (self.num_vertices, 3):
            raise ValueError(
                f"vertices must be [{self.num_vertices},3] or [B,{self.num_vertices},3] (this avatar's body), "
                f"got {tuple(vertices.shape)}"
            )
        # Frames for the faces in use only (binding faces; far fewer than N after densification).
        vertices, faces = vertices.to(self.means.dtype), self.faces[self.binding_faces]
        return face_table(vertices, faces) if kernels else FaceTable.rows(*triangle_frames(vertices, faces))

    def _posed(self, vertices: torch.Tensor | None, table: torch.Tensor | None = None) -> torch.Tensor:
        """Every Gaussian's row g [N,FACE_TABLE] of the posed mesh's face table (``compose_gaussians`` reads it).
        ``table``: :meth:`face_table` of ``vertices``, when the caller has it (then ``vertices`` is not read)."""
        if table is None:
            if vertices is None or vertices.dim() != 2:
                raise ValueError(f"vertices must be [{self.num_vertices},3] (this avatar's body), got "
                                 f"{None if vertices is None else tuple(vertices.shape)}")
            table = self.face_table(vertices)
        elif table.shape != (self.binding_faces.shape[0], FACE_TABLE):
            raise ValueError(f"table must be [{self.binding_faces.shape[0]},{FACE_TABLE}] (face_table of one "
                             f"mesh), got {tuple(table.shape)}")
        return posed_rows(table, self.face_slot())

    def pose_input(self, body_pose: torch.Tensor, hand_pose: torch.Tensor | None = None) -> torch.Tensor:
        """The rectifier's pose input ``[..., pose_dim]`` from ``body_pose [..., 69]`` and ``hand_pose
        [..., 90]`` (None: the relaxed hands): body_pose itself unless the rectifier sees the hands."""
        if self.pose_dim == POSE_DIM:
            return body_pose
        if hand_pose is None:
            hand_pose = self.relaxed_hand_pose.expand(*body_pose.shape[:-1], HAND_POSE_DIM)
        return torch.cat([body_pose, hand_pose.to(body_pose)], -1)

    def rectify(self, vertices: torch.Tensor, body_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The rectifier's raw outputs (d_mu, d_s, d_r) for a posed mesh ``vertices`` [V,3] and
        ``body_pose`` [69]: in the triangles' frames for the local design, in world units for the
        paper's; what :meth:`forward` takes as ``rectified``."""
        if self.rectifier is None:
            raise ValueError("this avatar has no rectifier")
        # a design whose input does not depend on the posed mesh does not pose it
        return self._rectify(self._posed(vertices) if self.rectifier.reads_posed_mesh else None, body_pose)

    def _rectify(self, g: torch.Tensor | None, body_pose: torch.Tensor | None):
        """The design's raw outputs for face rows ``g`` as from :meth:`_posed` (None where the design does not
        read the posed mesh), after checking ``body_pose``."""
        if body_pose is None:
            raise ValueError(f"this avatar has a rectifier: forward needs its pose input [{self.pose_dim}]")
        body_pose = torch.as_tensor(body_pose, dtype=self.means.dtype, device=self.means.device).reshape(-1)
        if body_pose.numel() != self.pose_dim:
            raise ValueError(f"the rectifier's pose input must have {self.pose_dim} values (pose_input), "
                             f"got {body_pose.numel()}")
        return self.rectifier.rectify(self, g, body_pose)

    def forward(self, vertices: torch.Tensor | None, body_pose: torch.Tensor | None = None,
                rectified: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                table: torch.Tensor | None = None) -> GaussianSet:
        """World-space Gaussians for a posed mesh (:meth:`forward_with_extras` without the extras)."""
        return self.forward_with_extras(vertices, body_pose, rectified, table)[0]

    def forward_with_extras(self, vertices: torch.Tensor | None, body_pose: torch.Tensor | None = None,
                            rectified: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                            table: torch.Tensor | None = None) -> tuple[GaussianSet, "AvatarExtras"]:
        """World-space Gaussians for a posed mesh, and what the training losses read besides them.
        vertices [V,3], body_pose [69] (the rectifier's pose input; may be None only without a
        rectifier, or with ``rectified``); rectified: the rectifier's raw outputs from :meth:`rectify` to
        use instead of running it (test-time pose fitting holds them fixed between refreshes); table:
        :meth:`face_table` of ``vertices`` (training passes each frame's, computed once; ``vertices`` may
        then be None)."""
        g = self._posed(vertices, table)
        raw = None
        if self.rectifier is not None:
            raw = rectified if rectified is not None else self._rectify(g, body_pose)
        # the design says in which frame its offsets live (compose_gaussians brings them to world units)
        mu, r, s, frames, offsets = compose_gaussians(g, self.means, self.quats, self.log_scales, raw,
                                                      self.rectifier, self.config.min_scale)
        deg = host_scalar(self, "active_sh_degree", int)
        k = (deg + 1) ** 2
        # all stored bands on: the whole tensor, not a slice (whose backward would copy into zeros)
        rest = self.sh_rest if k - 1 == self.sh_rest.shape[1] else self.sh_rest[:, : k - 1]
        sh = self.sh_dc if k == 1 else torch.cat((self.sh_dc, rest), dim=1)
        gs = GaussianSet(means=mu, quats=r, scales=s, opacities=self.opacities(), sh=sh, sh_degree=deg, frames=frames)
        return gs, AvatarExtras(local_means=self.means, local_log_scales=self.log_scales, offsets=offsets,
                                row_weights=self.row_weights)

    @torch.no_grad()
    def world_gaussians(self, vertices: torch.Tensor, body_pose: torch.Tensor | None = None) -> GaussianSet:
        """Export-ready world-space Gaussians: rectifier on, evaluation mode, no autograd, all
        stored SH bands."""
        was_training = self.training
        self.eval()
        try:
            out = self.forward(vertices, body_pose)
        finally:
            self.train(was_training)
        out.sh = torch.cat((self.sh_dc, self.sh_rest), dim=1).detach()
        out.sh_degree = self.config.sh_degree
        return out

    # ------------------------------------------------------------------ resizing (checkpoints)
    def resize_(self, n: int) -> None:
        """Replace every per-Gaussian tensor with an uninitialised one of ``n`` rows (for loading a
        densified checkpoint). Optimisers built before this hold stale parameters: rebuild them."""
        for name in GAUSSIAN_PARAMS:
            old = getattr(self, name)
            setattr(self, name, nn.Parameter(old.new_empty((n,) + tuple(old.shape[1:]))))
        self.face_ids = self.face_ids.new_zeros(n)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Like nn.Module's, but first resizes the per-Gaussian tensors to the stored count."""
        if "means" in state_dict and state_dict["means"].shape[0] != self.num_gaussians:
            self.resize_(state_dict["means"].shape[0])
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


@torch.no_grad()
def drawable_copy(avatar: Avatar) -> Avatar:
    """A copy of ``avatar`` holding only the Gaussians a rasterizer can draw, and only the binding faces
    they sit on, for work that holds the avatar still and poses it many times (pose fits, and every use of
    a trained avatar: ``load_trained``). An avatar with nothing to draw, or nothing to leave out (no
    faint Gaussian, no capacity buffers: a drawable copy already), is returned as it is.

    A Gaussian's alpha at a pixel is at most its opacity, and every backend skips alphas under
    ``ALPHA_MIN`` (1/255, as 3DGS and gsplat): one with a lower opacity adds nothing to any image or
    gradient. Density control prunes only below its own threshold (0.005) and an opacity reset leaves
    every opacity at most 0.01, so many Gaussians are such: about a third of those of the trained avatars
    measured (docs/evaluate.md, "Test-time pose fitting").
    Every kept Gaussian is posed, rectified and coloured as in ``avatar`` (each row on its own), so the
    copy renders the same images; its parameters are detached copies, without capacity buffers."""
    keep = avatar.opacities() >= ALPHA_MIN  # capacity buffers' unused rows are drawn at opacity 0
    if not keep.any() or (avatar.live is None and keep.all()):
        return avatar
    used = torch.unique(avatar.face_slot()[keep])
    out = copy.copy(avatar)  # a shallow copy: the shared buffers and the rectifier stay shared
    out._parameters, out._buffers = dict(avatar._parameters), dict(avatar._buffers)
    for name in GAUSSIAN_PARAMS:
        out._parameters[name] = nn.Parameter(getattr(avatar, name)[keep].detach(), requires_grad=False)
    out._buffers["face_ids"] = avatar.face_ids[keep]
    out._buffers["binding_faces"] = avatar.binding_faces[used]
    for name in ("rest_frames", "rest_scales", "rest_centroids"):
        out._buffers[name] = getattr(avatar, name)[used]
    out._buffers["live"] = out._buffers["row_weights"] = None
    out.live_rows = None
    out.rows = RowGathers()  # other rows: gathers of their own
    return out
